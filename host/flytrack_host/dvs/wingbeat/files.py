"""Event files in and out of the wing-beat commands: a NumPy `.npy` of the event layout, or any file
the event readers and writers handle (AEDAT 2/3.1/4, EVT 2/3, DAT). Shared by cli.py and live_cli.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def load_events(path: Path) -> np.ndarray:
    """Events from a NumPy `.npy` of the event layout, or any event file the event readers open
    (AEDAT 2/3.1/4, EVT 2/3, DAT)."""
    from flytrack_host.dvs.events.files import EVENT_DTYPE, read_events

    if path.suffix == ".npy":
        ev = np.load(path, allow_pickle=False)
        if ev.dtype.names is None or not {"t", "x", "y", "p"} <= set(ev.dtype.names):
            raise ValueError(f"{path}: a .npy of events needs fields t, x, y, p (got {ev.dtype})")
        out = np.zeros(len(ev), dtype=EVENT_DTYPE)
        for f in ("t", "x", "y", "p"):
            out[f] = ev[f]
        return out
    return read_events(path)


def save_events(path: Path, events: np.ndarray, width: int, height: int) -> None:
    if path.suffix == ".npy":
        np.save(path, events)
        return
    from flytrack_host.dvs.events.files import EventWriter

    with EventWriter(path, width=width, height=height) as w:
        w.write(events)
