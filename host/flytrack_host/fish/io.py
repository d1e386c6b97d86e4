"""HDF5 output of fish tracks: per fish per frame the raw fit, the filtered and the smoothed state
(position, heading, midline parameters), its covariance, curvature along the body and in total (eq. 5.2),
which cameras saw it, the frame its model was made in (states before it are NaN: not yet modelled),
and each fish's shape model (cross-sections a, b, d at s)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np

from flytrack_host.fish.curvature import S_GRID, curvature, detect_fast_starts, total_curvature
from flytrack_host.fish.pipeline import TrackResult

FORMAT = "flytrack-fish/1"


def write_tracks(path: Path, res: TrackResult, cameras: Sequence[str]) -> None:
    """Write atomically (to a temporary name, then renamed) so a killed run leaves no half file."""
    tmp = path.with_name(path.name + ".part")
    with h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["fps"] = res.fps
        f.attrs["first_frame"] = res.first_frame
        f.attrs["cameras"] = ",".join(cameras)
        f.attrs["state_layout"] = "r (3, m), h (3, unit heading), p (5, m): seed 004 eqs 3.1-3.2"
        f.attrs["messages"] = "\n".join(res.messages)
        T = res.smoothed.shape[0]
        f["frame"] = res.first_frame + np.arange(T)
        f["time_s"] = (res.first_frame + np.arange(T)) / res.fps
        mf = np.asarray(res.model_frame, np.int64)
        if mf.size != res.n_fish:
            mf = np.zeros(res.n_fish, np.int64)
        for i, model in enumerate(res.models):
            g = f.create_group(f"fish_{i}")
            # frames before the fish's model was made: not yet modelled, NaN states and seen 0
            g.attrs["model_frame"] = int(res.first_frame + mf[i])
            sm = res.smoothed[:, i]
            g["position"] = sm[:, 0:3]
            g["heading"] = sm[:, 3:6]
            g["midline_p"] = sm[:, 6:11]
            g["covariance"] = res.covariance[:, i]
            g["raw_state"] = res.raw[:, i]
            g["filtered_state"] = res.filtered[:, i]
            g["seen"] = res.seen[:, i]
            g["occlusion_group_size"] = res.shared[:, i]
            g["curvature_s"] = S_GRID
            g["curvature"] = curvature(sm[:, 6:11])
            g["total_curvature"] = total_curvature(sm[:, 6:11])
            m = g.create_group("model")
            m["s"] = model.s
            m["a"] = model.a
            m["b"] = model.b
            m["d"] = model.d
            m.attrs["length"] = model.length
            starts = detect_fast_starts(sm[mf[i]:, 6:11], res.fps, model.length, i)
            g["fast_start_onset"] = np.array([s.onset + mf[i] + res.first_frame for s in starts], dtype=np.int64)
            g["fast_start_kind"] = np.array([s.kind for s in starts], dtype="S7")
    tmp.replace(path)


def read_tracks(path: Path) -> dict:
    """The file's fish groups as dicts of arrays (for tests and analysis)."""
    out: dict = {}
    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != FORMAT:
            raise ValueError(f"{path}: not a FlyTrack fish track file (format {f.attrs.get('format')!r})")
        out["fps"] = float(f.attrs["fps"])
        out["frame"] = f["frame"][()]
        out["fish"] = []
        for name in sorted(k for k in f if k.startswith("fish_")):
            g = f[name]
            fish = {k: g[k][()] for k in g if not isinstance(g[k], h5py.Group)}
            fish["model_frame"] = int(g.attrs.get("model_frame", f.attrs["first_frame"]))
            out["fish"].append(fish)
    return out
