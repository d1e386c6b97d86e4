"""`flytrack calibrate dvs-points`: DVS cameras calibrated with the frame cameras from a blinking LED
(calibration/led_events.py finds it; sim/dvs_wand.py simulates it, sim/dvs_calibration.py has `dvs-sim`).

Commands of the `calibrate` typer app (cli_common.py); calibration/cli.py imports this module at its end so
they are registered.
"""

from __future__ import annotations

import csv
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from flytrack_host.calibration.cli_common import InputError, _clean_errors, _parse_size, app, console, err
from flytrack_host.calibration.led_events import EventOrderError, LedExtractor, LedParams, LedPoints, SyncError
from flytrack_host.calibration.observations import Observations, load_points, save_points


@dataclass
class DvsPointsResult:
    name: str
    size: tuple[int, int]
    points: LedPoints
    seconds: float  # reading and finding, wall time
    cpu_seconds: float  # the same, CPU time of this process (what the machine's load does not inflate)
    frequencies: list[tuple[float, float]]
    damaged: str | None  # the reader's message when the file is damaged (the events before were used)


def _read_sync_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """frame,t_us rows (t_us on the event camera's clock): the pulses' frames and times."""
    if not path.exists():
        raise InputError(f"--sync {path}: no such file.")
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    rows = list(csv.DictReader(lines))
    if not rows or not {"frame", "t_us"} <= set(rows[0]):
        raise InputError(f"--sync {path}: expected a CSV with the header frame,t_us (trigger frame number, "
                         "pulse time in microseconds on the event camera's clock) and at least two rows.")
    try:
        frames = np.array([int(r["frame"]) for r in rows], np.int64)
        t = np.array([int(float(r["t_us"])) for r in rows], np.int64)
    except (TypeError, ValueError):
        raise InputError(f"--sync {path}: a frame or t_us value is not a number.") from None
    if len(t) < 2 or np.any(np.diff(t) <= 0) or np.any(np.diff(frames) <= 0):
        raise InputError(f"--sync {path}: needs at least two rows with frame and t_us both increasing.")
    return frames, t


def extract_file(path: Path, name: str, params: LedParams, size: tuple[int, int] | None = None,
                 first_frame: int = 0, sync_csv: tuple[np.ndarray, np.ndarray] | None = None,
                 progress: Progress | None = None) -> DvsPointsResult:
    """The LED's points in one event file (streamed in chunks), stamped with trigger frames from the
    file's sync events (or from sync_csv: frames and pulse times)."""
    from flytrack_host.dvs.events import EventFileError, EventReader

    if not path.exists():
        raise InputError(f"{path}: no such file.")
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        reader = EventReader(path, triggers=True)
    except EventFileError as exc:
        raise InputError(f"{path}: not an event file this reader opens ({exc}). Give an EVT 2.0/3.0, DAT or "
                         "AEDAT 2/3/4 recording of the DVS camera.") from None
    damaged = None
    with reader as r:
        info = r.info
        w, h = size if size else (info.width, info.height)
        if w <= 0 or h <= 0:
            raise InputError(f"{path}: the file does not give the sensor size; pass --size WIDTHxHEIGHT.")
        ex = LedExtractor(w, h, params)
        if sync_csv is not None:  # all pulse times known up front
            ex.feed(_empty(), sync_csv[1])
        total = max(1, os.path.getsize(path))
        task = progress.add_task(name, total=total) if progress is not None else None
        try:
            while (chunk := r.read_chunk()) is not None:
                trig = r.read_triggers()
                sync = trig["t"][trig["value"] == 1] if sync_csv is None else None
                ex.feed(chunk, sync)
                if progress is not None and task is not None:
                    progress.update(task, completed=r.info.offset)
        except EventFileError as exc:  # keep what came before the damage
            damaged = str(exc)
        except EventOrderError as exc:
            raise InputError(f"{path}: {exc}") from None
        trig = r.read_triggers()  # those after the last events
        ex.feed(_empty(), trig["t"][trig["value"] == 1] if sync_csv is None else None)
        if progress is not None and task is not None:
            progress.update(task, completed=total)
        n_trig = r.info.n_triggers
    if sync_csv is None and ex.stats["events"] and not len(ex._sync_all):
        how = (f"{n_trig} trigger events, none a rising edge" if n_trig else "no sync (external trigger) events")
        raise InputError(f"{path}: {how}, so its event times cannot be tied to trigger frames. Wire the trigger "
                         "output to the camera's sync input while recording, or give --sync FRAMES.csv "
                         "(frame,t_us).")
    try:
        pts = ex.finish(first_frame=first_frame, frames=sync_csv[0] if sync_csv is not None else None)
    except SyncError as exc:
        raise InputError(f"{path}: {exc}") from None
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    # what the events repeat at, for the message when the LED is (almost) not found
    freqs = ex.frequencies() if pts.stats["points"] < 0.1 * max(1, pts.stats["syncs"]) else []
    return DvsPointsResult(name, (w, h), pts, wall, cpu, freqs, damaged)


def _empty() -> np.ndarray:
    from flytrack_host.dvs.events import EVENT_DTYPE

    return np.zeros(0, EVENT_DTYPE)


def to_observations(results: list[DvsPointsResult], base: Observations | None = None) -> Observations:
    """The DVS cameras' points (after the cameras of `base`, e.g. the frame cameras' points file)."""
    names = list(base.camera_names) if base is not None else []
    sizes = list(base.sizes) if base is not None else []
    frames = [base.frame] if base is not None else []
    cams = [base.cam] if base is not None else []
    uvs = [base.uv] if base is not None else []
    for res in results:
        if res.name in names:
            raise InputError(f"camera name {res.name!r} is already in the points file; name the DVS camera "
                             "otherwise with --camera.")
        ci = len(names)
        names.append(res.name)
        sizes.append(res.size)
        frames.append(res.points.frame)
        cams.append(np.full(len(res.points.frame), ci, np.int32))
        uvs.append(res.points.uv)
    frame = np.concatenate(frames) if frames else np.zeros(0, np.int64)
    order = np.argsort(frame, kind="stable")
    return Observations(frame[order], np.concatenate(cams)[order], np.concatenate(uvs).reshape(-1, 2)[order],
                        names, sizes)


def _freq_text(freqs: list[tuple[float, float]]) -> str:
    if not freqs:
        return "no repeating activity at all (too few events?)"
    return ", ".join(f"{f:.0f} Hz ({100 * s:.0f} %)" for f, s in freqs) + " of a pixel's same-polarity repeats"


@app.command("dvs-points")
@_clean_errors
def dvs_points_cmd(
    events: list[Path] = typer.Argument(..., help="Event file(s), one per DVS camera (EVT 2.0/3.0, DAT, AEDAT 2/3/4)."),
    led_hz: float = typer.Option(..., "--led-hz", help="The LED's blink frequency in Hz (square wave)."),
    out: Path = typer.Option(..., "--out", "-o", help="Points file to write (.csv or .npz), as selfcal reads it."),
    camera: list[str] = typer.Option([], help="Camera name per event file, in order (default: the file's stem)."),
    with_points: Path | None = typer.Option(None, "--with", help="The frame cameras' points file: written to OUT "
                                            "together with the DVS points (same trigger frame numbers)."),
    sync: Path | None = typer.Option(None, help="CSV frame,t_us of the trigger pulses on the DVS clock, instead of "
                                     "the file's sync events (one event file only)."),
    first_frame: int = typer.Option(0, help="Trigger frame number of the file's first sync event."),
    duty: float = typer.Option(0.5, help="Fraction of the period the LED is on; 0 not to check it."),
    tolerance: float = typer.Option(0.15, help="Relative tolerance on the LED's period (and on/off times)."),
    window_ms: float = typer.Option(0.0, help="Events within +-window/2 of a pulse form its point (default: 4 LED "
                                    "periods, at most 0.8 frame)."),
    radius: float = typer.Option(6.0, help="Events farther than this (px) from the window's median are dropped."),
    size: str | None = typer.Option(None, help="Sensor size WIDTHxHEIGHT when the file does not say."),
    no_frequency_check: bool = typer.Option(False, "--no-frequency-check", hidden=True,
                                            help="Take every event as the LED's (diagnosis only)."),
) -> None:
    """2D points of a blinking LED in DVS recordings, one per trigger frame, for `calibrate selfcal`.

    Per pixel, runs of ON events (switch-on) and OFF events (switch-off) that repeat at the LED's period
    are the LED; anything else (moving objects, other flicker, noise) is dropped. Around each sync
    event (trigger pulse) the LED's events give its subpixel position at the pulse, so the point has
    the pulse's trigger frame number and pairs with the frame cameras' points of that frame.
    """
    if camera and len(camera) != len(events):
        raise InputError(f"{len(camera)} --camera names for {len(events)} event files: give one per file, in order.")
    if sync is not None and len(events) != 1:
        raise InputError("--sync FRAMES.csv holds one camera's pulse times: give one event file with it.")
    try:
        params = LedParams(led_hz, tolerance=tolerance, duty=duty or None,
                           window_us=window_ms * 1000 if window_ms > 0 else None, radius_px=radius,
                           check_frequency=not no_frequency_check)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    wh = _parse_size(size) if size else None
    sync_csv = _read_sync_csv(sync) if sync is not None else None
    base = load_points(with_points) if with_points is not None else None
    names = camera or [p.stem for p in events]
    if len(set(names)) != len(names):
        raise InputError(f"two event files give the same camera name ({', '.join(names)}): name them with --camera.")
    taken = [n for n in names if base is not None and n in base.camera_names]
    if taken:
        raise InputError(f"camera name(s) {', '.join(taken)} already in the points file {with_points}; name the DVS "
                         "camera(s) otherwise with --camera.")
    results = []
    with Progress(TextColumn("[bold]{task.description}[/bold]"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                  TimeRemainingColumn(), console=err, transient=True) as prog:
        for path, name in zip(events, names, strict=True):
            results.append(extract_file(path, name, params, wh, first_frame, sync_csv, prog))
    for res in results:
        st = res.points.stats
        if res.damaged:
            err.print(f"warning: {res.damaged}; the events before the damage were used.", highlight=False)
        if st["points"] == 0:
            raise InputError(f"{res.name}: no LED blinking at {led_hz:g} Hz (+-{100 * tolerance:.0f} %) in "
                             f"{st['events']} events and {st['syncs']} frames. The events repeat most at: "
                             f"{_freq_text(res.frequencies)}. Check --led-hz (and --duty).")
        rate, cpu_rate = st["events"] / max(res.seconds, 1e-9), st["events"] / max(res.cpu_seconds, 1e-9)
        console.print(f"{res.name} ({res.size[0]}x{res.size[1]}): {st['events']} events read and searched in "
                      f"{res.seconds:.2f} s, {res.cpu_seconds:.2f} s CPU ({rate / 1e6:.2f} M events/s, "
                      f"{cpu_rate / 1e6:.2f} M per CPU second), "
                      f"{st['led_events']} near pulses at {led_hz:g} Hz; {st['points']} points in {st['syncs']} "
                      f"frames ({100 * st['points'] / max(1, st['syncs']):.0f} %), median "
                      f"{np.median(res.points.n_events):.0f} events each"
                      + (f"; {st['missed_syncs']} missed sync pulses skipped" if st["missed_syncs"] else ""),
                      highlight=False)
        if st["points"] < 0.1 * st["syncs"]:
            err.print(f"warning: {res.name}: the LED was found in only {st['points']} of {st['syncs']} frames; the "
                      f"events repeat most at {_freq_text(res.frequencies)}.", highlight=False)
    obs = to_observations(results, base)
    save_points(obs, out)
    console.print(f"written {out}: {len(obs.frame)} points of {', '.join(obs.camera_names)} "
                  "(next: flytrack calibrate selfcal " + str(out) + " -o cal.xml)", highlight=False)
