"""Rate-limited logging per kind of message, with counts.

A flood of one fault (random camera indices, garbage, a replaying edge) must not drown the log, and
must not stop later, different problems from being logged either. Each message has a kind, a short key
such as "unknown_camera" or "bad:10.0.0.5:BAD_MAGIC" that does not contain the varying value. Per
kind, the first message is logged at once. After that, at most one line per `interval_s` says how
many more came ("... (37 more since, 412 in all)"). Every kind is counted (`counts`). The number of
kinds is bounded: past `max_kinds`, new kinds share one "other" kind, so they are still logged
(rate-limited) and counted. Intervals come from the monotonic clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass
class _Kind:
    total: int = 0
    since: int = 0  # messages not logged since the last line
    last_logged: float = -1e18
    last_message: str = ""


class RateLimitedLog:
    def __init__(self, log: Callable[[str], None], interval_s: float = 5.0, max_kinds: int = 256) -> None:
        self.log = log
        self.interval_s = interval_s
        self.max_kinds = max_kinds
        self.kinds: dict[str, _Kind] = {}
        self.lines = 0  # lines actually logged

    @property
    def counts(self) -> dict[str, int]:
        return {k: v.total for k, v in self.kinds.items()}

    def __call__(self, kind: str, message: str, now: float | None = None) -> None:
        k = self.kinds.get(kind)
        if k is None:
            if len(self.kinds) >= self.max_kinds:
                kind = "other"
                k = self.kinds.get(kind)
            if k is None:
                k = self.kinds[kind] = _Kind()
        k.total += 1
        k.last_message = message
        t = time.monotonic() if now is None else now
        if t - k.last_logged < self.interval_s:
            k.since += 1
            return
        if k.total == 1:
            self.log(message)
        else:
            self.log(f"{message} ({k.since} more like this since the last report, {k.total} in all)")
        k.since = 0
        k.last_logged = t
        self.lines += 1

    def flush(self, now: float | None = None) -> None:
        """Log the counts not reported yet (at stop), one line per kind."""
        for k in self.kinds.values():
            if k.since:
                self.log(f"{k.last_message} ({k.since} more like this since the last report, {k.total} in all)")
                k.since = 0
                k.last_logged = time.monotonic() if now is None else now
                self.lines += 1
