"""Braid's `.braidz` archive: export a FlyTrack recording, import 2D data for re-tracking.

A .braidz is a zip of gzipped CSV tables plus `calibration.xml` (flydra XML), `braid_metadata.yml`
and a README, with Braid's file and column names (braid_types / flydra_types, schema 3):

- kalman_estimates: obj_id, frame, timestamp, x, y, z, xvel, yvel, zvel, P00 P01 P02 P11 P12 P22 P33 P44 P55
- data2d_distorted: camn, frame, timestamp, cam_received_timestamp, device_timestamp, block_id, x, y,
  area, slope, eccentricity, frame_pt_idx, cur_val, mean_val, sumsqf_val (no detection: empty x)
- data_association: obj_id, frame, cam_num, pt_idx
- cam_info: camn, cam_id
- trigger_clock_info: start_timestamp, framecount, tcnt, stop_timestamp
- textlog: mainbrain_timestamp, cam_id, host_timestamp, message. Braid's reader (braidz-parser) takes
  the frame rate from a line "MainBrain running at F fps, (...)" (F as Rust prints an f64, or
  "unknown"; without the parenthesis it refuses the archive) and the tracking parameters from a JSON
  line {"tracking_params": {...}, "git_revision": ...}, which it requires when kalman_estimates is
  present (TrackingParams denies unknown fields);
- experiment_info: uuid (one row per experiment UUID set during the run).

Missing values (an unknown trigger timestamp, a NaN coordinate, a zero device timestamp or camera
frame number, which Braid keeps as NonZeroU64) are written as empty fields, which Braid reads as
None / NaN. Rows FlyTrack could not map to a trigger frame (-1) and 2D rows the live run rejected are
left out (Braid's frame numbers are unsigned), counted in the returned counts (`<table> not exported:
...`), the archive's textlog and its README. Optional parts: `reconstruct_latency_usec.hlog` (trigger
to estimate, from the recording's latency table) and `reprojection_distance_100x_pixels.hlog` (each
associated 2D point's distance to its estimate's projection, x100), HdrHistogram logs (io/hdr.py), and
`images/<camera>.png` from the recording's background_<camera>.png files. Reading accepts a `.braidz`
and Braid's uncompressed `.braid` folder (the same files, written while it records).
Braid's camera numbers are u8: a camera index above 255 is an error. FlyTrack's orientation (radians) is
Braid's slope = tan(orientation). The export itself is in braidz_export.py (it reads a recording in
parts part by part).
"""

from __future__ import annotations

import gzip
import io
import json
import re
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd

from flytrack_host.io.braid_format import (
    ASSOC_COLUMNS,
    BRAID_SCHEMA,
    CAM_INFO_COLUMNS,
    CLOCK_COLUMNS,
    DATA2D_COLUMNS,
    DVS_POINTS,
    DVS_POINTS_COLUMNS,
    KALMAN_COLUMNS,
    TEXTLOG_COLUMNS,
    BraidzError,
    braid_tracking_params,
)
from flytrack_host.io.data2d import Data2D, empty_rows
from flytrack_host.recording.reader import Recording
from flytrack_host.recording.schema import DVS_COVARIANCE, FLAG_DVS
from flytrack_host.recording.source import RecordingSource, open_source

__all__ = ["ASSOC_COLUMNS", "BRAID_SCHEMA", "CAM_INFO_COLUMNS", "CLOCK_COLUMNS", "DATA2D_COLUMNS", "DVS_POINTS",
           "DVS_POINTS_COLUMNS", "KALMAN_COLUMNS", "TEXTLOG_COLUMNS", "BraidzError", "braid_tracking_params",
           "export_braidz", "read_braidz"]


def export_braidz(rec: Recording | RecordingSource | Path | str, out: Path | str) -> dict[str, int]:
    """Write a recording as a .braidz; returns rows written per table. `rec`: a recording's path (a
    recording in parts is read part by part, in bounded memory), a RecordingSource or a Recording."""
    from flytrack_host.io.braidz_export import export_source  # (it uses this module's names)

    return export_source(open_source(rec), Path(out))


# --- reading ----------------------------------------------------------------------------------


class _Folder:
    """Braid's uncompressed `.braid` folder, read like the zip it becomes."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def namelist(self) -> list[str]:
        return [p.relative_to(self.path).as_posix() for p in self.path.rglob("*") if p.is_file()]

    def read(self, name: str) -> bytes:
        return (self.path / name).read_bytes()

    def __enter__(self) -> _Folder:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


def _apply_dvs_points(data: Data2D, dp: pd.DataFrame) -> None:
    """Flag the rows FlyTrack's DVS table names as event-camera points and attach their covariances, as a
    FlyTrack recording carries them (FLAG_DVS, dvs_point_covariance)."""
    if not all(c in dp.columns for c in DVS_POINTS_COLUMNS) or not len(dp):
        return
    rows = data.rows

    def key(frame: np.ndarray, camn: np.ndarray, pt: np.ndarray) -> np.ndarray:
        return (frame.astype(np.int64) << 24) | (camn.astype(np.int64) << 8) | np.minimum(pt, 255).astype(np.int64)

    num = {c: pd.to_numeric(dp[c], errors="coerce").to_numpy(dtype=np.float64, na_value=np.nan)
           for c in DVS_POINTS_COLUMNS}
    ok = np.isfinite(num["frame"]) & np.isfinite(num["camn"]) & np.isfinite(num["frame_pt_idx"])
    k = key(num["frame"][ok], num["camn"][ok], num["frame_pt_idx"][ok])
    rows["flags"][np.isin(key(rows["trigger_frame"], rows["camera_index"], rows["frame_pt_idx"]), k)] |= FLAG_DVS
    has = ok & np.isfinite(num["var_x"]) & np.isfinite(num["var_y"]) & np.isfinite(num["cov_xy"])
    if has.any():
        cov = np.zeros(int(has.sum()), dtype=DVS_COVARIANCE)
        cov["trigger_frame"] = num["frame"][has]
        cov["camera_index"] = num["camn"][has]
        cov["frame_pt_idx"] = num["frame_pt_idx"][has]
        for c in ("var_x", "var_y", "cov_xy"):
            cov[c] = num[c][has]
        data.dvs_cov = cov


def _read_table(z: zipfile.ZipFile | _Folder, name: str) -> pd.DataFrame | None:
    names = set(z.namelist())
    # Braid archives may hold a top-level folder; accept "x/name" too.
    for cand in (f"{name}.csv", f"{name}.csv.gz"):
        hits = [n for n in names if n == cand or n.endswith("/" + cand)]
        if hits:
            data = z.read(hits[0])
            if cand.endswith(".gz"):
                try:
                    data = gzip.decompress(data)
                except (OSError, EOFError):
                    # A braid still being written may end in a cut gzip stream: keep what inflates.
                    data = _partial_gunzip(data)
            return pd.read_csv(io.BytesIO(data), comment=None)
    return None


def _partial_gunzip(data: bytes) -> bytes:
    import zlib

    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    out = d.decompress(data)
    return out[: out.rfind(b"\n") + 1]


def read_braidz(path: Path | str) -> Data2D:
    path = Path(path)
    z: zipfile.ZipFile | _Folder
    if path.is_dir():
        z = _Folder(path)
    else:
        try:
            z = zipfile.ZipFile(path)
        except (zipfile.BadZipFile, OSError) as exc:
            raise BraidzError(f"{path}: not a .braidz (zip) file: {exc}") from None
    with z:
        d2 = _read_table(z, "data2d_distorted")
        if d2 is None:
            raise BraidzError(f"{path}: no data2d_distorted table; not a Braid archive")
        missing = [c for c in ("camn", "frame", "x", "y") if c not in d2.columns]
        if missing:
            raise BraidzError(f"{path}: data2d_distorted lacks columns {missing}")
        ci = _read_table(z, "cam_info")
        names = {int(r.camn): str(r.cam_id) for r in ci.itertuples()} if ci is not None else {}
        cal = None
        for n in z.namelist():
            if n == "calibration.xml" or n.endswith("/calibration.xml"):
                cal = ("calibration.xml", z.read(n))
        clock = _read_table(z, "trigger_clock_info")
        dvs_points = _read_table(z, DVS_POINTS)
        fps, params = None, None
        tl = _read_table(z, "textlog")
        if tl is not None and "message" in tl.columns:
            for msg in tl["message"].astype(str):
                m = re.match(r"MainBrain running at ([0-9.eE+-]+) ", msg + " ")
                if m:
                    try:
                        fps = float(m.group(1))
                    except ValueError:
                        pass
                elif msg.startswith("{") and "tracking_params" in msg:
                    try:
                        params = json.loads(msg)["tracking_params"]
                    except (json.JSONDecodeError, KeyError, TypeError):
                        pass
    data = Data2D(rows=_rows_from_braid_df(d2), cam_names=names, fps=fps, calibration=cal,
                  source=str(path), tracking_params=None, notes=[f"braid tracking_params: {params}"] if params else [])
    if dvs_points is not None:
        _apply_dvs_points(data, dvs_points)
    if clock is not None and len(clock) and all(c in clock.columns for c in CLOCK_COLUMNS):
        data.clock_samples = np.array(
            list(clock[CLOCK_COLUMNS].itertuples(index=False, name=None)),
            dtype=[("start_timestamp", "<f8"), ("framecount", "<f8"), ("tcnt", "<f8"), ("stop_timestamp", "<f8")])
    return data


def _rows_from_braid_df(d2: pd.DataFrame) -> np.ndarray:
    """Braid/flydra data2d_distorted columns -> DATA2D rows (x_undist filled later from the calibration)."""
    n = len(d2)
    rows = empty_rows(n)

    def col(name: str, default: float = np.nan) -> np.ndarray:
        if name in d2.columns:
            return pd.to_numeric(d2[name], errors="coerce").to_numpy(dtype=np.float64, na_value=np.nan)
        return np.full(n, default)

    frame = col("frame", -1)
    rows["trigger_frame"] = np.where(np.isfinite(frame), frame, -1).astype(np.int64)
    rows["camera_index"] = col("camn", 0).astype(np.int64)
    block = col("block_id", 0)
    rows["camera_frame"] = np.where(np.isfinite(block), block, 0).astype(np.uint64)
    rows["timestamp"] = col("timestamp")
    rows["cam_received_timestamp"] = col("cam_received_timestamp")
    dev = col("device_timestamp", 0)
    rows["device_timestamp_ns"] = np.where(np.isfinite(dev), dev, 0).astype(np.uint64)
    rows["x_dist"] = col("x")
    rows["y_dist"] = col("y")
    rows["area"] = col("area")
    with np.errstate(invalid="ignore"):
        rows["orientation"] = np.arctan(col("slope"))
    rows["eccentricity"] = col("eccentricity")
    pt = col("frame_pt_idx", 0)
    rows["frame_pt_idx"] = np.where(np.isfinite(pt), pt, 0).astype(np.uint16)
    cv = col("cur_val", 0)
    rows["cur_val"] = np.where(np.isfinite(cv), cv, 0).astype(np.uint16)
    rows["mean_val"] = col("mean_val")
    rows["sumsq_val"] = col("sumsqf_val")
    return rows
