"""Import flydra's `.h5` (PyTables) 2D data, calibration, tracks and clock samples, faithfully.

Tables read (PyTables tables are HDF5 compound datasets, so h5py reads them): `data2d_distorted`
(camn, frame, timestamp, cam_received_timestamp, x, y, area, slope, eccentricity, frame_pt_idx, cur_val,
mean_val, sumsqf_val), `cam_info` (camn, cam_id), `textlog` (..., message), `kalman_estimates` (obj_id,
frame, timestamp, x, y, z, ...) and `trigger_clock_info` (start_timestamp, framecount, tcnt,
stop_timestamp).

The calibration group is read (geometry.formats.flydra_h5) as flydra's Reconstructor reads it:
- `calibration/pmat/<cam_id>` (3x4) is in the world units of `calibration/scale_factor2meters/<cam_id>`
  (e.g. 0.001: millimetres): P's last column is multiplied by it, so FlyTrack's world is in metres;
- `calibration/intrinsic_linear/<cam_id>` is the K about which flydra applies the distortion
  `calibration/intrinsic_nonlinear/<cam_id>` (k1, k2, p1, p2[, k3]); the linear part comes from P.
  That is Camera(K from P, K_dist = intrinsic_linear): flydra's projection exactly;
- `calibration/resolution/<cam_id>`; `calibration/refractive_interfaces` (a water surface z = 0, n2).
The frame rate comes from the textlog's "... running at N fps" line (as flydra and Braid write it).
"""

from __future__ import annotations

import re
from pathlib import Path

import h5py
import numpy as np
import pandas as pd

from flytrack_host.geometry.formats.flydra_h5 import FlydraH5Error, read_flydra_calibration
from flytrack_host.io.braidz import _rows_from_braid_df
from flytrack_host.io.data2d import Data2D

_FPS_RE = re.compile(r"running at\s+([0-9]+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)?)\s*fps")
_TOP_RE = re.compile(r"\btop\s+([0-9]+)\b")
_VERSION_RE = re.compile(r"using flydra version\s+([0-9]+(?:\.[0-9]+)*)")


def _text(v: object) -> str:
    return v.decode(errors="replace") if isinstance(v, bytes) else str(v)


def fps_from_textlog(messages: list[str]) -> float | None:
    """The frame rate of a flydra/Braid textlog ("MainBrain running at 100 fps, ..."), else None."""
    for msg in messages:
        m = _FPS_RE.search(msg)
        if m:
            v = float(m.group(1))
            if np.isfinite(v) and v > 0:
                return v
    return None




def clock_tcnt_scale(messages: list[str]) -> tuple[float | None, str]:
    """What `trigger_clock_info.tcnt` counts up to, as flydra's own time model reads it
    (result_utils.get_time_model_from_data): the textlog's "top N" when it has one (flydra before 0.5.3
    kept the raw timer value, e.g. 0..10000), else 255 for flydra 0.5.3 on (and Braid: the fraction
    of the frame x 255), else unknown (None). Returns (scale, what it was taken from)."""
    version = None
    for msg in messages:
        m = _TOP_RE.search(msg)
        if m and int(m.group(1)) > 0:
            return float(m.group(1)), f"the textlog's top {m.group(1)}"
        v = _VERSION_RE.search(msg)
        if v:
            version = tuple(int(x) for x in v.group(1).split("."))
    if version is None or version >= (0, 5, 3):
        return 255.0, "255 (flydra 0.5.3 on, Braid)"
    return None, f"flydra {'.'.join(map(str, version))} without a timer top in its textlog"


def _with_fraction(clock: np.ndarray, scale: float) -> np.ndarray:
    """The clock table with a `fraction` column (tcnt / scale) added."""
    names = clock.dtype.names or ()
    out = np.zeros(len(clock), dtype=[*clock.dtype.descr, ("fraction", "<f8")])
    for n in names:
        out[n] = clock[n]
    out["fraction"] = np.asarray(clock["tcnt"], dtype=np.float64) / scale
    return out


def _table(h5: h5py.File, name: str) -> np.ndarray | None:
    if name not in h5:
        return None
    obj = h5[name]
    if not isinstance(obj, h5py.Dataset) or obj.dtype.names is None:
        return None
    return obj[...]


def read_flydra_kalman(path: Path | str) -> pd.DataFrame | None:
    """flydra's own tracks (`kalman_estimates`: obj_id, frame, x, y, z, ...), positions in metres."""
    with h5py.File(path, "r") as h5:
        k = _table(h5, "kalman_estimates")
        if k is None:
            return None
        df = pd.DataFrame({n: k[n] for n in k.dtype.names if k[n].ndim == 1})
        # flydra writes kalman positions in metres (its reconstructor is scaled before tracking).
    return df


def read_flydra_association(path: Path | str) -> pd.DataFrame | None:
    """The 2D points flydra's tracks used (obj_id, frame, camn, pt_idx): `ML_estimates` (older files:
    `kalman_observations`) rows point with obs_2d_idx into the `ML_estimates_2d_idxs` VLArray, whose
    rows are flattened (camn, frame_pt_idx) pairs. None when the file has neither."""
    with h5py.File(path, "r") as h5:
        ml = _table(h5, "ML_estimates")
        if ml is None:
            ml = _table(h5, "kalman_observations")
        if ml is None or "ML_estimates_2d_idxs" not in h5 or "obs_2d_idx" not in (ml.dtype.names or ()):
            return None
        vl = h5["ML_estimates_2d_idxs"][...]
    obj, frame, camn, pt = [], [], [], []
    for o, f, i in zip(ml["obj_id"].tolist(), ml["frame"].tolist(), ml["obs_2d_idx"].tolist(), strict=True):
        if not 0 <= int(i) < len(vl):
            continue
        pairs = np.asarray(vl[int(i)], dtype=np.int64)
        for c, p in zip(pairs[0::2].tolist(), pairs[1::2].tolist(), strict=False):
            obj.append(int(o))
            frame.append(int(f))
            camn.append(c)
            pt.append(p)
    return pd.DataFrame({"obj_id": obj, "frame": frame, "camn": camn, "pt_idx": pt})


def read_flydra_h5(path: Path | str) -> Data2D:
    path = Path(path)
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise FlydraH5Error(f"{path}: not an HDF5 file: {exc}") from None
    notes: list[str] = []
    with h5:
        if "data2d_distorted" not in h5:
            raise FlydraH5Error(f"{path}: no data2d_distorted table; not a flydra 2D data file")
        raw = h5["data2d_distorted"][...]
        if raw.dtype.names is None or "camn" not in raw.dtype.names or "x" not in raw.dtype.names:
            raise FlydraH5Error(f"{path}: data2d_distorted is not a table with camn, frame, x, y columns")
        df = pd.DataFrame({n: raw[n] for n in raw.dtype.names})
        names: dict[int, str] = {}
        ci = _table(h5, "cam_info")
        if ci is not None:
            names = {int(r["camn"]): _text(r["cam_id"]) for r in ci}
        by_id = read_flydra_calibration(h5, notes)
        fps = None
        tl = _table(h5, "textlog")
        messages = [_text(m) for m in tl["message"]] if tl is not None and "message" in tl.dtype.names else []
        if messages:
            fps = fps_from_textlog(messages)
        for key in ("fps", "framerate"):
            if fps is None and key in h5.attrs:
                fps = float(h5.attrs[key])
        clock = _table(h5, "trigger_clock_info")
    rows = _rows_from_braid_df(df)
    cameras = {camn: by_id[cid] for camn, cid in names.items() if cid in by_id} if by_id else None
    if by_id and names:
        absent = sorted(cid for cid in names.values() if cid not in by_id)
        if absent:
            notes.append(f"camera(s) {', '.join(absent)} have 2D data but no calibration: their points are not used")
    data = Data2D(rows=rows, cam_names=names, fps=fps, calibration=None, source=str(path), cameras=cameras,
                  notes=notes)
    if clock is not None and len(clock):
        names = clock.dtype.names or ()
        if "tcnt" in names and "fraction" not in names:
            scale, source = clock_tcnt_scale(messages)
            if scale is None:
                notes.append(f"trigger clock: tcnt's range is unknown ({source}): samples not used")
                clock = None
            else:
                clock = _with_fraction(clock, scale)
                if scale != 255.0:
                    notes.append(f"trigger clock: tcnt is the timer's count up to {scale:g} ({source})")
        data.clock_samples = clock
    return data
