"""`flytrack trigger ...`: talk to the trigger box (FlyTrack firmware, simulator or strawlab)."""

from __future__ import annotations

import shlex
import shutil
import subprocess
import time
from pathlib import Path

import typer
from rich.console import Console

from flytrack_host.util import hostclock

from .common import TriggerError, check_port_exists
from .flash import BOARDS, avrdude_command, firmware_mcu

app = typer.Typer(help="Trigger box: info, start/stop, live clock figures, pulses, flashing.", no_args_is_help=True)
console = Console()
err = Console(stderr=True, soft_wrap=True)  # one line per message, whatever the terminal width

PortOpt = typer.Option("/dev/ttyUSB0", "--port", "-p", help="Serial port of the trigger box.")
KindOpt = typer.Option("flytrack", "--kind", help="flytrack (this firmware) or strawlab (triggerbox).")
WaitOpt = typer.Option(None, "--reset-wait", min=0.0, show_default=False,
                       help="Seconds to wait after opening (the Arduino resets on open): default 2 for flytrack, "
                            "7 for strawlab (its name handshake; it is then asked V? every second up to 20 s).")


def _open(port: str, kind: str, reset_wait: float | None):  # noqa: ANN202 - either driver
    try:
        if kind == "strawlab":
            from .strawlab import RESET_WAIT_S, StrawlabTriggerbox

            return StrawlabTriggerbox(port, reset_wait_s=RESET_WAIT_S if reset_wait is None else reset_wait)
        if kind != "flytrack":
            raise TriggerError(f"unknown --kind {kind!r} (flytrack or strawlab)")
        from .device import TriggerDevice

        return TriggerDevice(port, reset_wait_s=2.0 if reset_wait is None else reset_wait)
    except TriggerError as exc:
        err.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None


def _fail(exc: Exception) -> None:
    err.print(f"[red]error[/red] {exc}", highlight=False)
    raise typer.Exit(code=2)


@app.command()
def info(port: str = PortOpt, kind: str = KindOpt, reset_wait: float | None = WaitOpt) -> None:
    """Print what the device reports about itself."""
    with _open(port, kind, reset_wait) as dev:
        try:
            i = dev.info()
        except TriggerError as exc:
            _fail(exc)
        console.print(i, highlight=False)


@app.command()
def start(
    fps: float = typer.Option(..., "--fps", help="Frame rate asked for; the exact rate made is printed."),
    port: str = PortOpt, kind: str = KindOpt, reset_wait: float | None = WaitOpt,
) -> None:
    """Set the frame rate and start triggering."""
    with _open(port, kind, reset_wait) as dev:
        try:
            dev.stop()
            got = dev.set_rate(fps)
            dev.start()
        except TriggerError as exc:
            _fail(exc)
        r = dev.rate
        console.print(f"triggering at {got:.6f} fps (asked {fps:g}): prescaler /{r.divisor}, TOP {r.top}",
                      highlight=False)


@app.command()
def stop(port: str = PortOpt, kind: str = KindOpt, reset_wait: float | None = WaitOpt,
         reset: bool = typer.Option(False, "--reset", help="Also zero the frame count.")) -> None:
    """Stop triggering."""
    with _open(port, kind, reset_wait) as dev:
        try:
            dev.stop_reset() if reset else dev.stop()
        except TriggerError as exc:
            _fail(exc)
        console.print("stopped", highlight=False)


@app.command()
def watch(
    fps: float = typer.Option(100.0, "--fps", help="Frame rate (the device is restarted at it)."),
    seconds: float = typer.Option(10.0, "--seconds", min=0.0, help="How long to watch (0 = until Ctrl-C)."),
    period: float = typer.Option(0.05, "--period", min=0.001, help="Clock query period, s."),
    port: str = PortOpt, kind: str = KindOpt, reset_wait: float | None = WaitOpt,
) -> None:
    """Live clock-model figures: frame, gain, offset, residual, samples."""
    with _open(port, kind, reset_wait) as dev:
        try:
            dev.stop()
            dev.set_rate(fps)
            dev.start()
        except TriggerError as exc:
            _fail(exc)
        dev.start_clock_thread(period)
        t_end = time.monotonic() + seconds if seconds > 0 else float("inf")
        try:
            while time.monotonic() < t_end:
                time.sleep(1.0)
                m = dev.model
                if not m.fitted:
                    console.print("waiting for clock samples...", highlight=False)
                    continue
                frame = m.host_time_to_frame(hostclock.now())
                console.print(f"frame {frame:12.2f}  gain {m.gain:.9f}  offset {m.offset:.6f}  "
                              f"residual {m.residual_s * 1e6:7.1f} us  samples {m.n_samples}  "
                              f"rejected {m.rejected_rtt}", highlight=False)
        except KeyboardInterrupt:
            pass
        finally:
            dev.stop_clock_thread()


@app.command()
def pulse(
    frame: int = typer.Option(-1, "--frame", min=-1, help="Frame to pulse in (-1: the earliest reachable)."),
    width_ms: float = typer.Option(1.0, "--width-ms", help="Pulse width, ms."),
    channel: int = typer.Option(0, "--channel", min=0,
                                help="Output channel: 0 is the exact pulse output (D10, hardware/README.md)."),
    port: str = PortOpt, kind: str = KindOpt, reset_wait: float | None = WaitOpt,
    fps: float = typer.Option(100.0, "--fps", help="Frame rate the device runs at (to convert the width)."),
) -> None:
    """Fire a pulse (high-speed camera trigger) now or at a given frame."""
    with _open(port, kind, reset_wait) as dev:
        try:
            if dev.rate is None:
                dev.stop()
                dev.set_rate(fps)
                dev.start()
            ticks = dev.pulse(channel, None if frame < 0 else frame, width_ms / 1000.0)
        except TriggerError as exc:
            _fail(exc)
        console.print(f"pulse scheduled on channel {channel}: {ticks} ticks", highlight=False)


@app.command()
def flash(
    board: str = typer.Option("nano", "--board", help=f"One of: {', '.join(BOARDS)}."),
    port: str = PortOpt,
    hex_file: str = typer.Option("", "--hex", help="Firmware .hex (default: the build for the board's MCU)."),
    dry_run: bool = typer.Option(False, "--dry-run", help="Print the avrdude command, do not run it."),
) -> None:
    """Flash the firmware with avrdude through the Arduino bootloader."""
    from .simulator import build_dir

    try:
        path = hex_file or str(build_dir() / "firmware" / firmware_mcu(board) / "flytrack_trigger.hex")
        cmd = avrdude_command(board, port, path)
    except ValueError as exc:
        _fail(exc)
    if dry_run:  # the command only: nothing is checked
        console.print(shlex.join(cmd), highlight=False, soft_wrap=True)
        return
    # Clear messages for what avrdude would otherwise report in its own words (or a traceback).
    try:
        check_port_exists(port)
    except TriggerError as exc:
        _fail(exc)
    if not Path(path).is_file():
        _fail(TriggerError(f"firmware {path} is missing: run `make firmware` (or give --hex)"))
    if shutil.which(cmd[0]) is None:
        _fail(TriggerError("avrdude is not installed (apt-get install avrdude)"))
    console.print(shlex.join(cmd), highlight=False, soft_wrap=True)
    if BOARDS[board][1] == "avr109":
        console.print("touching the port at 1200 baud to enter the bootloader", highlight=False)
        import serial

        try:
            serial.Serial(port, 1200).close()
        except serial.SerialException as exc:
            _fail(TriggerError(f"cannot open {port}: {exc}"))
        time.sleep(2.0)
    rc = subprocess.run(cmd, check=False).returncode
    if rc != 0:
        err.print(f"[red]error[/red] avrdude failed (exit {rc}): its output is above", highlight=False)
    raise typer.Exit(code=rc)
