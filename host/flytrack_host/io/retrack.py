"""Offline re-tracking: run the tracker again over recorded 2D data, with other parameters.

Sources: a FlyTrack recording (folder or recording.h5), a `.braidz`, or a flydra `.h5`. The result
is a new FlyTrack recording (2D rows copied, new 3D estimates and associations), finalised to HDF5,
which `flytrack export` turns into .braidz or CSV like any other.

A FlyTrack recording in parts is re-tracked part by part (`load_2d(..., stream=True)`): the parts are
regrouped by frame (recording.stream) and fed in order to one tracker, whose state carries over from
part to part, so the estimates are those of the recording read whole; memory stays at about two parts.
The result is a recording in parts too, one part per part of the source.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError
from tqdm import tqdm

from flytrack_host.geometry.camera import Camera
from flytrack_host.io.data2d import Data2D, dvs_rows_left_out, fill_undistorted, iter_bundles, n_frames
from flytrack_host.recording.finalize import RecordingError
from flytrack_host.recording.parts import PartPolicy
from flytrack_host.recording.reader import load_recording
from flytrack_host.recording.schema import CAM_INFO, DATA2D, TRIGGER_CLOCK
from flytrack_host.recording.source import open_source
from flytrack_host.recording.stream import frame_blocks
from flytrack_host.recording.writer import Recorder
from flytrack_host.tracking.params import TrackingParams


class RetrackError(Exception):
    pass


SOURCE_SUFFIXES = (".h5", ".hdf5", ".braidz", ".braid", ".flytrack")


def default_output(source: Path | str) -> Path:
    """Where `flytrack retrack SOURCE` writes without --out: beside SOURCE, its name without the
    suffix of its kind (only that one: "sample_datafile-v0.4.28.h5" -> "sample_datafile-v0.4.28"), plus
    ".retrack.flytrack"."""
    source = Path(source)
    name = source.name
    for suffix in SOURCE_SUFFIXES:
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            name = name[: -len(suffix)]
            break
    return source.with_name(name + ".retrack.flytrack")


def data2d_from_recording(path: Path, stream: bool = False) -> Data2D:
    """2D data of a FlyTrack recording; with `stream` a recording in parts is not read here but part by
    part by `retrack` (Data2D.parts)."""
    if stream:
        src = open_source(path)
        if src.parted:
            return Data2D(rows=np.zeros(0, dtype=DATA2D), cam_names=_names(src.table("cam_info")), fps=src.fps,
                          calibration=src.calibration, source=str(path),
                          tracking_params=src.meta.get("tracking_params"), parts=src)
    rec = load_recording(path)
    names = _names(rec.table("cam_info"))
    dvs_cov = rec.table("dvs_point_covariance")
    return Data2D(rows=rec.table("data2d_distorted").copy(), cam_names=names, fps=rec.fps,
                  calibration=rec.calibration, source=str(path), tracking_params=rec.meta.get("tracking_params"),
                  dvs_cov=dvs_cov.copy() if len(dvs_cov) else None)


def _names(cam_info: np.ndarray) -> dict[int, str]:
    return {int(r["camera_index"]): r["calibration_id"].decode() or r["name"].decode() for r in cam_info}


def load_2d(path: Path | str, stream: bool = False) -> Data2D:
    """2D data from a FlyTrack recording, a .braidz or Braid's .braid folder, or a flydra .h5 (by content).
    `stream`: a FlyTrack recording in parts is left on disk for `retrack` to read part by part."""
    path = Path(path)
    if not path.exists():
        raise RetrackError(f"{path}: no such file or folder")
    is_braid_folder = path.is_dir() and (path.suffix == ".braid" or any(
        (path / n).exists() for n in ("data2d_distorted.csv.gz", "data2d_distorted.csv")))
    if path.suffix == ".braidz" or is_braid_folder or (path.is_file() and path.read_bytes()[:2] == b"PK"):
        from flytrack_host.io.braidz import read_braidz

        return read_braidz(path)
    try:
        return data2d_from_recording(path, stream=stream)
    except RecordingError:
        if path.is_file():
            from flytrack_host.io.flydra_h5 import read_flydra_h5

            return read_flydra_h5(path)
        raise RetrackError(f"{path}: not a FlyTrack recording, .braidz or flydra .h5") from None


def cameras_for(data: Data2D, calibration: Path | None = None, warnings: list[str] | None = None) -> dict[int, Camera]:
    """camera index -> Camera, from `calibration` (a file: flydra XML or .h5, pymvg, ...) or the calibration
    inside the data. Cameras with 2D data but no calibration are named in `warnings` (and data.notes)."""
    from flytrack_host.geometry.formats import load_calibration

    warns = warnings if warnings is not None else data.notes
    if calibration is not None:
        by_name = load_calibration(calibration, warns)
    elif data.cameras:
        return dict(data.cameras)
    elif data.calibration is not None:
        name, blob = data.calibration
        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / name
            p.write_bytes(blob)
            by_name = load_calibration(p, warns)
    else:
        raise RetrackError(f"{data.source}: holds no calibration; pass one with --calibration")
    cams = {idx: by_name[n] for idx, n in data.cam_names.items() if n in by_name}
    if not cams:
        raise RetrackError(f"no camera of {sorted(data.cam_names.values())} is in the calibration "
                           f"({sorted(by_name)})")
    absent = sorted(n for n in data.cam_names.values() if n not in by_name)
    if absent:
        warns.append(f"camera(s) {', '.join(absent)} have 2D data but no calibration: their points are not used")
    return cams


def calibration_xml(data: Data2D, cameras: Mapping[int, Camera]) -> bytes:
    """The cameras used, as flydra XML named as in the data (exact: K_dist and <water> included), so a
    retrack's output can be retracked again."""
    from flytrack_host.geometry.formats import save_flydra_xml

    by_name = {data.cam_names.get(i, cam.name): cam for i, cam in sorted(cameras.items())}
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "calibration.xml"
        save_flydra_xml(by_name, p)
        return p.read_bytes()


def clock_from_samples(data: Data2D, fps: float) -> tuple[np.ndarray | None, list[str]]:
    """The source's trigger clock samples through the clock model: early-frame samples corrected
    (clock_model.correct_clock_counts), a fit of host time on frame; rows without a timestamp get one
    from the fit. Returns corrected TRIGGER_CLOCK rows (or None) and log lines with the numbers."""
    from flytrack_host.trigger.clock_model import ClockModel, correct_clock_counts

    c = data.clock_samples
    if c is None or not len(c) or c.dtype.names is None:
        return None, []
    names = c.dtype.names
    if "framecount" not in names or "start_timestamp" not in names or "stop_timestamp" not in names:
        return None, ["trigger_clock_info lacks framecount/start_timestamp/stop_timestamp: not used"]
    t0 = np.asarray(c["start_timestamp"], dtype=np.float64)
    t1 = np.asarray(c["stop_timestamp"], dtype=np.float64)
    frac = (np.asarray(c["fraction"], dtype=np.float64) if "fraction" in names
            else np.asarray(c["tcnt"], dtype=np.float64) / 255.0)
    corr = correct_clock_counts(np.asarray(c["framecount"], dtype=np.float64), frac, 0.5 * (t0 + t1), rtt=t1 - t0)

    def fit(frames: np.ndarray) -> ClockModel:
        m = ClockModel(frame_period_s=1.0 / fps, window=max(len(c), 2), max_rtt_s=0.02)
        m.fit_batch(t0, t1, frames / fps)  # once over the recording (refitting per sample is O(n^2))
        return m

    model = fit(corr.frames)
    # A constant count offset (firmware numbering: the count of the pulse under way rather than of the
    # frame) shows against the 2D rows' own trigger timestamps: frame f's timestamp sits at sample count
    # f + k on the fit. Detected when the rows agree on one integer k to within 0.2 frames.
    offset_line = ""
    rows = data.rows
    ts_ok = np.isfinite(rows["timestamp"]) & (rows["trigger_frame"] >= 0)
    if model.fitted and ts_ok.sum() >= 3:
        sel = np.flatnonzero(ts_ok)[:: max(1, int(ts_ok.sum()) // 2000)]
        lag = np.array([model.host_time_to_frame(float(t)) for t in rows["timestamp"][sel]])
        lag -= rows["trigger_frame"][sel]
        k = int(np.round(np.median(lag)))
        if k != 0 and np.percentile(np.abs(lag - k), 90) < 0.2:
            corr.frames = corr.frames - k
            model = fit(corr.frames)
            offset_line = (f"; count offset {k:+d} frame(s) against the 2D rows' trigger timestamps detected and "
                           "removed")
    out = np.zeros(len(c), dtype=TRIGGER_CLOCK)
    out["start_timestamp"], out["stop_timestamp"] = t0, t1
    out["framecount"] = np.floor(corr.frames).astype(np.int64)
    out["fraction"] = corr.frames - np.floor(corr.frames)
    mark = (f", the count stepping {100 * corr.mark:.1f} % into the frame (found from the samples)"
            if corr.early_fixed and np.isfinite(corr.mark) else "")
    lines = [f"trigger clock: {len(c)} samples, {corr.early_fixed} taken early in a frame (count not yet "
             f"incremented{mark}) corrected by one frame{offset_line}"]
    if corr.note:
        lines.append(f"trigger clock: {corr.note}")
    if model.fitted:
        lines[0] += (f"; fit residual {model.residual_s * 1e6:.0f} us, gain {model.gain:.8f}")
        rows = data.rows
        need = ~np.isfinite(rows["timestamp"]) & (rows["trigger_frame"] >= 0)
        if need.any():
            rows["timestamp"][need] = [model.frame_to_host_time(float(f)) for f in rows["trigger_frame"][need]]
            lines.append(f"trigger clock: {int(need.sum())} 2D rows without a timestamp got one from the fit")
    return out, lines


def params_with(base: dict | None, toml_path: Path | None = None, sets: list[str] | None = None) -> TrackingParams:
    """Tracking parameters: `base` (e.g. the live run's), then a TOML file ([tracking] table or
    top-level keys), then `key=value` overrides. Unknown keys are errors (pydantic)."""
    import tomllib

    values: dict[str, Any] = dict(base or {})
    if toml_path is not None:
        try:
            data = tomllib.loads(Path(toml_path).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise RetrackError(f"--params {toml_path}: {why}; expected a TOML file whose tracking table "
                               "holds the parameters, e.g. motion_noise_scale = 0.2") from None
        values.update(data.get("tracking", data))
    for s in sets or []:
        key, sep, val = s.partition("=")
        if not sep:
            raise RetrackError(f"--set {s!r}: write KEY=VALUE, e.g. motion_noise_scale=0.2")
        try:
            values[key.strip()] = tomllib.loads(f"v = {val.strip()}")["v"] if val.strip() else val
        except tomllib.TOMLDecodeError:
            values[key.strip()] = val.strip()  # not a TOML value: the check below names the key and the type
    try:
        return TrackingParams.model_validate(values)
    except ValidationError as exc:
        errs = "; ".join(f"{'.'.join(str(x) for x in e['loc'])} = {e.get('input')!r}: {e['msg']}"
                         for e in exc.errors())
        raise RetrackError(f"tracking parameters: {errs}") from None
    except Exception as exc:
        raise RetrackError(f"tracking parameters: {exc}") from None


@dataclass
class RetrackResult:
    frames: int
    estimates: int
    objects: int
    out: Path | None
    seconds: float
    tracker_path: str = "numpy"  # "c" or "numpy": which tracker implementation ran
    stats: dict[str, int] | None = None
    why_nothing: list[str] | None = None  # reasons, with numbers, when points arrived but nothing tracked
    notes: list[str] | None = None  # what the run said on the way (clock fit, missing calibration, ...)


def _blocks(data: Data2D) -> Iterator[tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]:
    """(2D rows, their DVS covariances, rows too late to track) per block: the whole source at once, or a
    recording in parts regrouped by frame part by part (recording.stream)."""
    if data.parts is None:
        yield data.rows, data.dvs_cov, None
        return
    for b in frame_blocks(data.parts.iter_tables(["data2d_distorted", "dvs_point_covariance"])):
        cov = b.tables["dvs_point_covariance"]
        yield b.tables["data2d_distorted"], cov if len(cov) else None, b.late.get("data2d_distorted")


def retrack(
    data: Data2D,
    cameras: Mapping[int, Camera],
    params: TrackingParams,
    fps: float,
    out: Path | None = None,
    progress: bool = True,
    tracker_factory: Callable[..., Any] | None = None,
    on_result: Callable[[Any], object] | None = None,
) -> RetrackResult:
    if tracker_factory is None:
        from flytrack_host.tracking.tracker import Tracker as tracker_factory  # noqa: N813
    parted = data.parts is not None
    tracker = tracker_factory(cameras, params, 1.0 / fps)
    clock, clock_lines = clock_from_samples(data, fps)
    notes = list(data.notes) + clock_lines
    if not parted:
        fill_undistorted(data.rows, cameras)
        left_out = dvs_rows_left_out(data.rows, data.dvs_cov)
        if left_out:
            notes.append(_left_out_note(left_out))
    rec = None
    if out is not None:
        rec = Recorder(out, flush_interval_s=1.0, on_full="block", parts=PartPolicy() if parted else None, meta={
            "rig_name": f"retrack of {Path(data.source).name}", "fps": fps,
            "tracking_params": params.model_dump(), "retracked_from": data.source, "saving_program": "flytrack retrack",
        })
        rec.start()
        _start_output(rec, data, cameras, fps, params, tracker, notes)
        if clock is not None:
            rec.append("trigger_clock_info", clock)
    from flytrack_host.recording.rows import result_rows

    t0 = time.perf_counter()
    n = n_estimates = late = left_out_parts = 0
    ids: set[int] = set()
    with_points: set[int] = set()
    cams = sorted(data.cam_names) or None
    total = None if parted else n_frames(data.rows, data.dvs_cov)
    bar = tqdm(total=total, disable=not progress, unit="frame", desc="retrack")
    for k, (rows, dvs_cov, too_late) in enumerate(_blocks(data)):
        if parted:
            fill_undistorted(rows, cameras)
            left_out_parts += dvs_rows_left_out(rows, dvs_cov)
            if k and rec is not None:
                rec.new_part()  # the result's parts follow the source's
        if rec is not None:
            rec.append("data2d_distorted", rows)
            if dvs_cov is not None:
                rec.append("dvs_point_covariance", dvs_cov)
            if too_late is not None and len(too_late):
                rec.append("data2d_distorted", too_late)  # copied, not tracked (their frame was)
        if too_late is not None:
            late += len(too_late)
        ok = np.isfinite(rows["x_dist"]) & np.isfinite(rows["y_dist"])
        with_points.update(int(c) for c in np.unique(rows["camera_index"][ok]))
        for bundle in iter_bundles(rows, fps, cams, dvs_cov):
            result = tracker.process(bundle)
            n += 1
            n_estimates += len(result.estimates)
            ids.update(e.obj_id for e in result.estimates)
            if rec is not None:
                k_rows, a_rows = result_rows(result, bundle.timestamp)
                rec.append("kalman_estimates", k_rows)
                rec.append("data_association", a_rows)
            if on_result is not None:
                on_result(result)
            bar.update(1)
    bar.close()
    dt = time.perf_counter() - t0
    end_notes = [_left_out_note(left_out_parts)] if left_out_parts else []
    if late:
        end_notes.append(f"{late} 2D rows came more than a part after their frame (whose bundle was tracked "
                         "already): copied, not tracked")
    notes += end_notes
    stats = dict(getattr(tracker, "stats", {}) or {})
    why: list[str] = []
    if n_estimates == 0 and stats:
        from flytrack_host.tracking.diagnosis import why_no_estimates

        why = why_no_estimates(stats, cameras, params,
                               cameras_with_points=[c for c in sorted(with_points) if c in cameras])
    h5 = None
    if rec is not None:
        for line in end_notes:
            rec.log(line)
        rec.log(f"retrack done: {n} frames, {n_estimates} estimates, {len(ids)} objects in {dt:.2f} s")
        for w in why:
            rec.log(f"no estimates: {w}")
        h5 = rec.stop(finalize=True)
    return RetrackResult(frames=n, estimates=n_estimates, objects=len(ids), out=h5, seconds=dt,
                         tracker_path=getattr(tracker, "kernel_path", "numpy"), stats=stats, why_nothing=why,
                         notes=notes)


def _left_out_note(n: int) -> str:
    return (f"{n} event-camera points left out: the source has no covariance for them "
            "(recorded before FlyTrack kept it), and the tracker weighs them by it")


def _start_output(rec: Recorder, data: Data2D, cameras: Mapping[int, Camera], fps: float, params: TrackingParams,
                  tracker: Any, notes: list[str]) -> None:
    """The result's first rows: the calibration used (it travels with the result, so that it can be
    retracked again), cam_info, and the text log's opening lines."""
    from flytrack_host.geometry.formats import CalibrationFormatError

    try:
        rec.attach("calibration.xml", calibration_xml(data, cameras))
    except CalibrationFormatError as exc:  # e.g. tank-wall interfaces flydra XML cannot hold
        if data.calibration is not None:
            rec.attach(data.calibration[0], data.calibration[1])
        notes.append(f"the calibration used could not be written as flydra XML ({exc}); "
                     + ("the source's calibration file is attached instead" if data.calibration is not None
                        else "the result carries no calibration"))
    ci = np.zeros(len(data.cam_names), dtype=CAM_INFO)
    for i, (idx, name) in enumerate(sorted(data.cam_names.items())):
        ci[i] = (idx, name.encode()[:64], b"", name.encode()[:64])
    rec.append("cam_info", ci)
    rec.log(f"MainBrain running at {fps:g} fps")
    rec.log(f"retracked from {data.source} with {params.model_dump_json()}")
    path = getattr(tracker, "kernel_path", "numpy")
    rec.log(f"tracker: {'C kernel' if path == 'c' else 'NumPy'} path")
    for line in notes:
        rec.log(line)
