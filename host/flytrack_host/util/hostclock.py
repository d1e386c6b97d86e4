"""The host's clock seam: every host module reads the time here, nowhere else.

`now()` is host time in seconds: the monotonic clock shifted by an offset fixed once, when this module
is imported, so it reads like Unix time (recording timestamps look like dates) but it never steps. An
NTP step or a user setting the date does not move it. Every interval, and every time that two modules
compare (a frame's arrival, the trigger clock model's samples, an estimate's time, latency, the
fixed-rate clock's anchor), is on this timeline.

`wall()` is the system's wall clock. It is used only as a label: text log lines and the recording's
start date. `host_to_wall(t)` maps a host time to the wall clock through the offset measured now.
`check_wall()` notices wall-clock steps: the gap between wall() and now() moving by more than
`STEP_THRESHOLD_S` is one step. It is reported once, with its size and a running count.

Test seam: the real system clock cannot be stepped safely here (that needs root, and it disturbs every
process on the machine). So `wall()` adds a test offset. The environment variable
`FLYTRACK_FAULT_WALL_STEPS="8:-1,10:3600"` steps the wall clock this process sees by -1 s at 8 s after
import, then by +3600 s at 10 s. `step_wall(d)` steps it at once from inside the process. A fault test
uses them to step the wall clock inside a real running `flytrack demo` or `flytrack run`. If any host
module took an interval from the wall clock, such a test would catch it.
"""

from __future__ import annotations

import os
import threading
import time

ENV_STEPS = "FLYTRACK_FAULT_WALL_STEPS"
STEP_THRESHOLD_S = 0.2  # wall - host moving by more than this is a step (NTP slews far slower)


def _parse_steps(text: str) -> list[tuple[float, float]]:
    """"t:d,t:d" -> [(t, d)] sorted by t; a malformed entry is a clear ValueError."""
    steps = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        try:
            t, d = part.split(":")
            steps.append((float(t), float(d)))
        except ValueError:
            raise ValueError(f"{ENV_STEPS}: {part!r} is not AT_SECONDS:STEP_SECONDS (e.g. 8:-1)") from None
    return sorted(steps)


class HostClock:
    def __init__(self, steps: list[tuple[float, float]] | None = None) -> None:
        self._mono0 = time.monotonic()
        self._offset = time.time() - self._mono0  # fixed for the life of the process
        self._test_step = 0.0
        self._scheduled = list(steps or [])
        self._lock = threading.Lock()
        self._wall_gap = 0.0  # wall() - now() when last checked
        self.steps_seen = 0
        self.steps_total_s = 0.0

    def now(self) -> float:
        """Host time (s): monotonic, never steps; reads like Unix time."""
        return time.monotonic() + self._offset

    def mono(self) -> float:
        return time.monotonic()

    def wall(self) -> float:
        """The wall clock (plus any test step): a label only, never an interval."""
        if self._scheduled:
            self._apply_scheduled()
        return time.time() + self._test_step

    def host_to_wall(self, t: float) -> float:
        return t + (self.wall() - self.now())

    def step_wall(self, seconds: float) -> None:
        """Test seam: step the wall clock this process sees (the system clock is not touched)."""
        with self._lock:
            self._test_step += seconds

    def _apply_scheduled(self) -> None:
        elapsed = time.monotonic() - self._mono0
        with self._lock:
            while self._scheduled and self._scheduled[0][0] <= elapsed:
                self._test_step += self._scheduled.pop(0)[1]

    def check_wall(self) -> float | None:
        """The size of a wall-clock step since the last call (s), or None when there was none."""
        gap = self.wall() - self.now()
        d = gap - self._wall_gap
        if abs(d) <= STEP_THRESHOLD_S:
            self._wall_gap += 0.1 * d  # follow NTP's slow slewing
            return None
        self._wall_gap = gap
        self.steps_seen += 1
        self.steps_total_s += d
        return d


CLOCK = HostClock(_parse_steps(os.environ.get(ENV_STEPS, "")))


def now() -> float:
    return CLOCK.now()


def wall() -> float:
    return CLOCK.wall()


def wall_step_message(d: float) -> str:
    return (f"host wall clock stepped by {d:+.3f} s (step {CLOCK.steps_seen}); timing is unaffected "
            "(host time is monotonic), only wall-clock labels move")
