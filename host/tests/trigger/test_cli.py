from __future__ import annotations

import os
import subprocess
import sys

from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.trigger.flash import avrdude_command
from flytrack_host.trigger.software import SoftwareTrigger

runner = CliRunner()


def test_flash_dry_run_builds_avrdude_command() -> None:
    r = runner.invoke(app, ["trigger", "flash", "--board", "nano", "--port", "/dev/ttyUSB3", "--dry-run"])
    assert r.exit_code == 0, r.output
    assert "avrdude -p atmega328p -c arduino -P /dev/ttyUSB3 -b 115200 -D -U flash:w:" in r.output
    assert "atmega328p/flytrack_trigger.hex:i" in r.output
    cmd = avrdude_command("leonardo", "/dev/ttyACM0", "fw.hex")
    assert cmd[:6] == ["avrdude", "-p", "atmega32u4", "-c", "avr109", "-P"]
    r = runner.invoke(app, ["trigger", "flash", "--board", "mega", "--dry-run"])
    assert r.exit_code == 2


def test_info_start_pulse_stop_on_software_trigger() -> None:
    with SoftwareTrigger() as sw:
        common = ["--port", sw.port, "--reset-wait", "0"]
        r = runner.invoke(app, ["trigger", "info", *common])
        assert r.exit_code == 0 and "software-trigger" in r.output
        r = runner.invoke(app, ["trigger", "start", "--fps", "120", *common])
        assert r.exit_code == 0 and "119.997600 fps (asked 120)" in r.output
        r = runner.invoke(app, ["trigger", "watch", "--fps", "120", "--seconds", "1.5", "--period", "0.02", *common])
        assert r.exit_code == 0 and "residual" in r.output
        r = runner.invoke(app, ["trigger", "pulse", "--width-ms", "0.5", *common])
        assert r.exit_code == 0 and "pulse scheduled" in r.output
        r = runner.invoke(app, ["trigger", "stop", *common])
        assert r.exit_code == 0


def test_missing_port_exit_code() -> None:
    r = runner.invoke(app, ["trigger", "info", "--port", "/dev/nope-trigger", "--reset-wait", "0"])
    assert r.exit_code == 2


def _flytrack(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """The real command line in its own process: exit code, stdout and stderr as a user sees them."""
    return subprocess.run([sys.executable, "-m", "flytrack_host.cli", *args], capture_output=True, text=True,
                          timeout=60, env={**os.environ, **(env or {})})


def test_flash_checks_the_port_before_avrdude() -> None:
    r = _flytrack("trigger", "flash", "--port", "/dev/nonexistent-flytrack")
    assert r.returncode == 2, r.stdout + r.stderr
    assert "serial port /dev/nonexistent-flytrack does not exist (is the board plugged in?)" in r.stderr
    assert "Traceback" not in r.stderr and "avrdude" not in r.stdout + r.stderr  # avrdude never ran
    # --dry-run prints the command and checks nothing.
    r = _flytrack("trigger", "flash", "--port", "/dev/nonexistent-flytrack", "--dry-run")
    assert r.returncode == 0 and "avrdude -p atmega328p" in r.stdout and "-P /dev/nonexistent-flytrack" in r.stdout
    # A port that exists but no firmware file: said so, avrdude not run.
    r = _flytrack("trigger", "flash", "--port", os.devnull, "--hex", "/nonexistent/fw.hex")
    assert r.returncode == 2 and "firmware /nonexistent/fw.hex is missing" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and "avrdude -p" not in r.stdout


def test_numeric_options_are_range_checked() -> None:
    for args, opt in ((["watch", "--seconds", "-1"], "--seconds"), (["watch", "--period", "0"], "--period"),
                      (["info", "--reset-wait", "-1"], "--reset-wait"), (["pulse", "--frame", "-2"], "--frame"),
                      (["pulse", "--channel", "-1"], "--channel")):
        r = runner.invoke(app, ["trigger", *args, "--port", "/dev/nonexistent-flytrack"])
        assert r.exit_code == 2 and f"Invalid value for '{opt}'" in r.output, (args, r.output)


def test_pulse_width_must_be_positive() -> None:
    with SoftwareTrigger() as sw:
        r = _flytrack("trigger", "pulse", "--width-ms", "-1", "--port", sw.port, "--reset-wait", "0")
    assert r.returncode == 2 and "pulse width must be positive" in r.stderr, r.stdout + r.stderr
    assert "Traceback" not in r.stderr
