from __future__ import annotations

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
