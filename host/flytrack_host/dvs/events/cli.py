"""`flytrack events ...`: inspect event-camera files and convert them to AEDAT 4.0 or EVT 3.0."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from flytrack_host.dvs.events.files import COMPRESSIONS, FORMATS, EventFileError, EventReader, EventWriter

app = typer.Typer(help="Event-camera files: info, convert.", no_args_is_help=True)
console = Console()


def _fail(msg: str) -> typer.Exit:
    console.print(f"[red]error[/red] {msg}", highlight=False)
    return typer.Exit(code=2)


@app.command("info")
def info(
    path: Path = typer.Argument(..., help="An event file: AEDAT 2.0/3.1/4.0, EVT 2.0/3.0 (.raw), DAT."),
    fmt: str = typer.Option("auto", "--format", help=f"auto or one of {', '.join(FORMATS)}."),
) -> None:
    """Read the whole file and print its format, sensor size, event count, time span and polarity
    balance. A damaged file prints what came before the damage, then the error (exit 2)."""
    n = on = 0
    t0 = t1 = None
    err: EventFileError | None = None
    try:
        with EventReader(path, None if fmt == "auto" else fmt) as r:
            try:
                for c in r:
                    n += len(c)
                    on += int(np.count_nonzero(c["p"]))
                    t0 = int(c["t"][0]) if t0 is None else t0
                    t1 = int(c["t"][-1])
            except EventFileError as exc:
                err = exc
            i = r.info
    except (EventFileError, ValueError) as exc:
        raise _fail(str(exc)) from None
    span = f"{t0} .. {t1} us ({(t1 - t0) / 1e6:.3f} s)" if t0 is not None and t1 is not None else "-"
    console.print(f"{path}: {i.format}" + (f" ({i.compression})" if i.format == "aedat4" else ""),
                  highlight=False)
    console.print(f"  sensor {i.width}x{i.height}" if i.width else "  sensor size not in the header")
    console.print(f"  {n:,} events, {on:,} ON / {n - on:,} OFF; time {span}", highlight=False)
    console.print(f"  {i.n_triggers:,} trigger/sync events; {i.n_skipped:,} other units skipped")
    if i.time_offset:
        console.print(f"  times include the header's time_offset_us {i.time_offset:,}", highlight=False)
    if err is not None:
        raise _fail(f"{err} (the {n:,} events before it are counted above)")


@app.command("convert")
def convert(
    src: Path = typer.Argument(..., help="The event file to read (any format `flytrack events info` reads)."),
    dst: Path = typer.Argument(..., help="The file to write: .aedat4 (AEDAT 4.0) or .raw (EVT 3.0)."),
    fmt: str = typer.Option("auto", "--format", help="Input format: auto or one of " + ", ".join(FORMATS) + "."),
    out_fmt: str = typer.Option("", "--to", help="Output format aedat4 or evt3 (default: from the name)."),
    compression: str = typer.Option("lz4", help="AEDAT 4.0 compression: " + ", ".join(COMPRESSIONS) + "."),
    width: int = typer.Option(0, help="Sensor width when the input's header does not give it."),
    height: int = typer.Option(0, help="Sensor height when the input's header does not give it."),
) -> None:
    """Convert an event file to AEDAT 4.0 (readable by dv-processing) or EVT 3.0, streaming, with its
    external trigger events: EVT 3.0 EXT_TRIGGER words, an AEDAT 4.0 trigger stream. What the output
    cannot hold is said (AEDAT 4.0 triggers have no channel id; EVT 3.0 channels are 0-15). A damaged
    input converts every event before the damage, then reports it (exit 2)."""
    out = out_fmt or ("evt3" if dst.suffix == ".raw" else "aedat4")
    if dst.resolve() == src.resolve():
        raise _fail(f"{dst}: the output would overwrite the input")
    try:
        reader = EventReader(src, None if fmt == "auto" else fmt, triggers=True)
    except (EventFileError, ValueError) as exc:
        raise _fail(str(exc)) from None
    with reader:
        w, h = width or reader.info.width, height or reader.info.height
        if not (w and h):
            raise _fail(f"{src}: the header gives no sensor size; pass --width and --height")
        try:
            writer = EventWriter(dst, w, h, out, compression, triggers=True)
        except (EventFileError, ValueError) as exc:
            raise _fail(str(exc)) from None
        damage: EventFileError | None = None
        size = os.path.getsize(src)
        trig = _TriggerTally(out)
        with writer, Progress(TextColumn("{task.description}"), BarColumn(), TimeRemainingColumn(),
                              console=console, transient=True) as bar:
            task = bar.add_task(f"{src.name} -> {dst.name}", total=size)
            try:
                for chunk in reader:
                    # the triggers decoded with this chunk first: EVT 3.0 holds them until the
                    # events pass their times, so both go out in time order
                    trig.write(writer, reader.read_triggers())
                    writer.write(chunk)
                    bar.update(task, completed=reader.info.offset)
            except EventFileError as exc:
                damage = exc
            except ValueError as exc:  # out of time order, or addresses the output cannot hold
                raise _fail(f"{dst}: {exc}") from None
            trig.write(writer, reader.read_triggers())  # those after the last event
        console.print(f"[green]wrote[/green] {dst}: {writer.n_written:,} events and {writer.n_triggers:,} triggers "
                      f"({out}" + (f", {compression}" if out == "aedat4" else "") + ")", highlight=False)
        for note in trig.notes():
            console.print(f"  [yellow]note[/yellow] {note}", highlight=False)
        if writer.time_offset:
            console.print(f"  times rebased: {writer.time_offset:,} us (the whole 2^24 us ranges before the first "
                          f"event) taken off every time and kept in the header as % time_offset_us "
                          f"{writer.time_offset}; `flytrack events` adds it back", highlight=False)
        if damage is not None:
            raise _fail(f"{damage} (the {writer.n_written:,} events before it were converted)")


class _TriggerTally:
    """What of the input's triggers the output format could not hold, for the closing notes."""

    def __init__(self, out: str) -> None:
        self.out = out
        self.channels: set[int] = set()  # AEDAT 4.0: channels other than 0, written without it
        self.n_channel_lost = 0
        self.too_high: dict[int, int] = {}  # EVT 3.0: channel -> triggers left out
        self.out_of_order = 0

    def write(self, writer: EventWriter, tr: np.ndarray) -> None:
        if not len(tr):
            return
        ch = tr["channel"].astype(np.int64)
        if self.out == "aedat4":
            self.channels.update(int(c) for c in np.unique(ch[ch != 0]))
            self.n_channel_lost += int(np.count_nonzero(ch))
        else:
            for c in np.unique(ch[ch > 15]):
                self.too_high[int(c)] = self.too_high.get(int(c), 0) + int(np.count_nonzero(ch == c))
        dropped = writer.write_triggers(tr)
        self.out_of_order += dropped - (int(np.count_nonzero(ch > 15)) if self.out == "evt3" else 0)

    def notes(self) -> list[str]:
        out = []
        if self.n_channel_lost:
            out.append(f"{self.n_channel_lost:,} triggers came on input channels "
                       f"{', '.join(map(str, sorted(self.channels)))}: AEDAT 4.0 triggers carry no channel id, so they "
                       "were written without it")
        for c, n in sorted(self.too_high.items()):
            out.append(f"{n:,} trigger{'s' if n != 1 else ''} on channel {c} cannot be written: EVT 3.0 trigger "
                       "channels are 0-15")
        if self.out_of_order:
            out.append(f"{self.out_of_order:,} triggers cannot be written: their time is before what the "
                       f"{'trigger stream' if self.out == 'aedat4' else 'file'} had already reached (out of time "
                       "order in the input)")
        return out
