"""Rows of a recording in parts, regrouped by trigger frame: every frame's rows in one block.

Within a part, the rows of a tracked frame are together (the pipeline queues them as one item and the
writer never splits an item). But rows can come after their frame: a camera frame that arrived late
(FLAG_LATE) is recorded when it comes, which can be in the next part. A reader that works frame by
frame (re-tracking, an export sorted by frame) reads the parts in order with one part of look-ahead:
from the rows read so far it hands on those of frames below the lowest frame of the next part, and
carries the rest on. The blocks then hold each frame's rows whole, in the order a whole read of the
recording gives them, and a stable sort by frame of each block gives exactly the sort of the whole.

Rows with no frame (trigger_frame < 0) and rows rejected live (FLAG_REJECTED) take no part in the
ordering: they go out with the block of their part. A row whose frame was handed on already (it came
more than a part late, e.g. after a minute-long network stall at a part boundary) cannot join it: it is
given in `late` of the block it came in, and the readers count it.

Memory: the rows carried (frames still open at a part's end), the part, and the next part.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.recording.schema import FLAG_REJECTED


@dataclass
class FrameBlock:
    tables: dict[str, np.ndarray]  # rows of frames [after, below), and unordered rows, in file order
    late: dict[str, np.ndarray] = field(default_factory=dict)  # rows of frames handed on in an earlier block
    below: float = np.inf  # this block holds the (ordered) rows of frames below this

    @property
    def n_late(self) -> int:
        return sum(len(v) for v in self.late.values())


def _ordered(rows: np.ndarray) -> np.ndarray:
    """The rows that take part in the frame order."""
    ok = rows["trigger_frame"] >= 0
    if rows.dtype.names and "flags" in rows.dtype.names:
        ok &= (rows["flags"] & FLAG_REJECTED) == 0
    return ok


def _lowest_frame(tables: dict[str, np.ndarray], at_least: float | None) -> float | None:
    """The lowest frame of the ordered rows (those below `at_least` left out: they come too late anyway,
    and must not hold back what can be handed on)."""
    lows = []
    for t in tables.values():
        ok = _ordered(t)
        if at_least is not None:
            ok &= t["trigger_frame"] >= at_least
        if ok.any():
            lows.append(float(t["trigger_frame"][ok].min()))
    return min(lows) if lows else None


def frame_blocks(parts: Iterable[dict[str, np.ndarray]]) -> Iterator[FrameBlock]:
    """One FrameBlock per part (tables with a `trigger_frame` column; the same names in every part)."""
    it = iter(parts)
    cur = next(it, None)
    carry: dict[str, np.ndarray] = {}
    done_below: float | None = None  # frames below this were handed on
    while cur is not None:
        nxt = next(it, None)
        buf: dict[str, np.ndarray] = {}
        late: dict[str, np.ndarray] = {}
        for name, rows in cur.items():
            if done_below is not None:
                is_late = _ordered(rows) & (rows["trigger_frame"] < done_below)
                if is_late.any():
                    late[name] = rows[is_late]
                    rows = rows[~is_late]
            buf[name] = np.concatenate([carry[name], rows]) if name in carry and len(carry[name]) else rows
        if nxt is None:
            below = np.inf
        else:
            low = _lowest_frame(nxt, done_below)
            # An empty next part tells nothing: hold everything (a later part may still hold rows of it).
            below = low if low is not None else (done_below if done_below is not None else -np.inf)
            if done_below is not None:
                below = max(below, done_below)
        block, carry = {}, {}
        for name, rows in buf.items():
            out = ~_ordered(rows) | (rows["trigger_frame"] < below)
            block[name] = rows[out]
            carry[name] = rows[~out]
        yield FrameBlock(block, late, below)
        done_below = below
        cur = nxt
