"""Offline re-tracking: run the tracker again over recorded 2D data, with other parameters.

Sources: a FlyTrack recording (folder or recording.h5), a `.braidz`, or a flydra `.h5`. The result
is a new FlyTrack recording (2D rows copied, new 3D estimates and associations), finalised to HDF5,
which `flytrack export` turns into .braidz or CSV like any other.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError
from tqdm import tqdm

from flytrack_host.camera import Camera
from flytrack_host.io.data2d import Data2D, fill_undistorted, iter_bundles, n_frames
from flytrack_host.recording.finalize import RecordingError
from flytrack_host.recording.reader import load_recording
from flytrack_host.recording.schema import CAM_INFO
from flytrack_host.recording.writer import Recorder
from flytrack_host.tracking.params import TrackingParams


class RetrackError(Exception):
    pass


def data2d_from_recording(path: Path) -> Data2D:
    rec = load_recording(path)
    names = {}
    for r in rec.table("cam_info"):
        names[int(r["camera_index"])] = r["calibration_id"].decode() or r["name"].decode()
    return Data2D(rows=rec.table("data2d_distorted").copy(), cam_names=names, fps=rec.fps,
                  calibration=rec.calibration, source=str(path), tracking_params=rec.meta.get("tracking_params"))


def load_2d(path: Path | str) -> Data2D:
    """2D data from a FlyTrack recording, a .braidz or a flydra .h5 (chosen by content)."""
    path = Path(path)
    if not path.exists():
        raise RetrackError(f"{path}: no such file or folder")
    if path.suffix == ".braidz" or (path.is_file() and path.read_bytes()[:2] == b"PK"):
        from flytrack_host.io.braidz import read_braidz

        return read_braidz(path)
    try:
        return data2d_from_recording(path)
    except RecordingError:
        if path.is_file():
            from flytrack_host.io.flydra_h5 import read_flydra_h5

            return read_flydra_h5(path)
        raise RetrackError(f"{path}: not a FlyTrack recording, .braidz or flydra .h5") from None


def cameras_for(data: Data2D, calibration: Path | None = None) -> dict[int, Camera]:
    """camera index -> Camera, from `calibration` (a file) or the calibration inside the data."""
    from flytrack_host.calibration.formats import load_calibration

    if calibration is not None:
        by_name = load_calibration(calibration)
    elif data.cameras:
        return dict(data.cameras)
    elif data.calibration is not None:
        name, blob = data.calibration
        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / name
            p.write_bytes(blob)
            by_name = load_calibration(p)
    else:
        raise RetrackError(f"{data.source}: holds no calibration; pass one with --calibration")
    cams = {idx: by_name[n] for idx, n in data.cam_names.items() if n in by_name}
    if not cams:
        raise RetrackError(f"no camera of {sorted(data.cam_names.values())} is in the calibration "
                           f"({sorted(by_name)})")
    return cams


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
    rows = data.rows
    fill_undistorted(rows, cameras)
    tracker = tracker_factory(cameras, params, 1.0 / fps)
    rec = None
    if out is not None:
        rec = Recorder(out, flush_interval_s=1.0, on_full="block", meta={
            "rig_name": f"retrack of {Path(data.source).name}", "fps": fps,
            "tracking_params": params.model_dump(), "retracked_from": data.source, "saving_program": "flytrack retrack",
        })
        rec.start()
        if data.calibration is not None:
            rec.attach(data.calibration[0], data.calibration[1])
        ci = np.zeros(len(data.cam_names), dtype=CAM_INFO)
        for i, (idx, name) in enumerate(sorted(data.cam_names.items())):
            ci[i] = (idx, name.encode()[:64], b"", name.encode()[:64])
        rec.append("cam_info", ci)
        rec.log(f"MainBrain running at {fps:g} fps")
        rec.log(f"retracked from {data.source} with {params.model_dump_json()}")
        rec.append("data2d_distorted", rows)
    from flytrack_host.pipeline import result_rows

    t0 = time.perf_counter()
    n = n_estimates = 0
    ids: set[int] = set()
    cams = sorted(data.cam_names) or None
    for bundle in tqdm(iter_bundles(rows, fps, cams), total=n_frames(rows), disable=not progress,
                       unit="frame", desc="retrack"):
        result = tracker.process(bundle)
        n += 1
        n_estimates += len(result.estimates)
        ids.update(e.obj_id for e in result.estimates)
        if rec is not None:
            k, a = result_rows(result, bundle.timestamp)
            rec.append("kalman_estimates", k)
            rec.append("data_association", a)
        if on_result is not None:
            on_result(result)
    dt = time.perf_counter() - t0
    h5 = None
    if rec is not None:
        rec.log(f"retrack done: {n} frames, {n_estimates} estimates, {len(ids)} objects in {dt:.2f} s")
        h5 = rec.stop(finalize=True)
    return RetrackResult(frames=n, estimates=n_estimates, objects=len(ids), out=h5, seconds=dt)
