"""Sliding windows of a camera's recent samples with their running minimum and maximum, read by the
early-frame, mapped-ahead and drift checks without walking the window."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable

import numpy as np


class _Window(deque):
    """Recent tuples of a camera, oldest first, that also keeps the smallest and largest of their
    values at index 1 (sliding-window minimum and maximum: `_lo` / `_hi` hold the tuples no later one
    undercuts / exceeds). Used for the (arrival, lag to the trigger clock) pairs, whose minimum the
    early-frame and mapped-ahead checks read several times a frame, and the drift samples (trigger
    frame, d, arrival), whose range decides most frames without a median. Walking the window each
    time cost up to 0.1 ms on the frame that completes a bundle."""

    def __init__(self, items: Iterable[tuple] = ()):
        super().__init__()
        self._lo: deque[tuple] = deque()
        self._hi: deque[tuple] = deque()
        for it in items:
            self.append(it)

    def append(self, item: tuple) -> None:
        super().append(item)
        v = item[1]
        lo, hi = self._lo, self._hi
        while lo and lo[-1][1] >= v:
            lo.pop()
        lo.append(item)
        while hi and hi[-1][1] <= v:
            hi.pop()
        hi.append(item)

    def popleft(self) -> tuple:
        item = super().popleft()
        if self._lo and self._lo[0] is item:
            self._lo.popleft()
        if self._hi and self._hi[0] is item:
            self._hi.popleft()
        return item

    def clear(self) -> None:
        super().clear()
        self._lo.clear()
        self._hi.clear()

    def min1(self) -> float:
        """The smallest value at index 1 (the window must not be empty)."""
        return self._lo[0][1]

    def max1(self) -> float:
        """The largest value at index 1 (the window must not be empty)."""
        return self._hi[0][1]


class _LagWindow(_Window):
    """The (arrival, lag to the trigger clock, trigger frame) window of a camera, which also keeps its
    arrivals and trigger frames in NumPy rings: the mapped-ahead check re-reads every camera's lags
    under the clock model as it is now, and walking the tuples in Python took 0.2-0.5 ms (about one
    such check lands on every trigger frame, five cameras at 20 Hz each)."""

    def __init__(self, items: Iterable[tuple] = ()):
        self._t = np.empty(128)
        self._f = np.empty(128)
        self._start = 0
        super().__init__(items)

    def append(self, item: tuple) -> None:
        super().append(item)
        n, cap = len(self), len(self._t)
        if n > cap:  # grow: the ring's contents oldest first, then room
            idx = (self._start + np.arange(n - 1)) % cap
            t, f = np.empty(2 * cap), np.empty(2 * cap)
            t[:n - 1], f[:n - 1] = self._t[idx], self._f[idx]
            self._t, self._f, self._start, cap = t, f, 0, 2 * cap
        i = (self._start + n - 1) % cap
        self._t[i] = item[0]
        self._f[i] = item[2]

    def popleft(self) -> tuple:
        item = super().popleft()
        self._start = (self._start + 1) % len(self._t)
        return item

    def clear(self) -> None:
        super().clear()
        self._start = 0

    def min_lag(self, t_ref: float, ref: int, slope: float, since: float = -math.inf) -> float:
        """min over the entries that arrived at or after `since` of arrival - (t_ref + (frame - ref) *
        slope), the same arithmetic as `FrameSynchronizer._lag_now` (trigger frames are exact in
        float64); inf when none did."""
        n, cap, s = len(self), len(self._t), self._start
        if n == 0:
            return math.inf
        if s + n <= cap:
            t, f = self._t[s:s + n], self._f[s:s + n]
        else:
            t = np.concatenate((self._t[s:], self._t[:s + n - cap]))
            f = np.concatenate((self._f[s:], self._f[:s + n - cap]))
        lag = t - (t_ref + (f - ref) * slope)
        if since > -math.inf:
            lag = lag[t >= since]
        return float(lag.min()) if len(lag) else math.inf
