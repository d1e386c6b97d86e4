"""When does the live host call the trigger lost: not on one late reply, yes on a dead port."""

from __future__ import annotations

import serial

from flytrack_host.rig import TriggerConfig
from flytrack_host.trigger.common import TriggerError
from flytrack_host.trigger.session import LOST_AFTER_FAILURES, TriggerSession


class FlakyDevice:
    """Stands in for TriggerDevice's clock query only: raises the queued errors, then fails forever."""

    def __init__(self, errors: list[BaseException]) -> None:
        self.errors = errors

    def query_clock(self):  # noqa: ANN201 - only the exception path is exercised
        raise self.errors.pop(0) if self.errors else TriggerError("no reply")


def session_with(device: FlakyDevice) -> TriggerSession:
    s = TriggerSession(TriggerConfig(kind="software"))
    s.device = device  # type: ignore[assignment]
    return s


def test_one_missed_reply_is_not_a_lost_trigger() -> None:
    s = session_with(FlakyDevice([TriggerError("timeout")]))
    s._sample()
    assert s.lost_since is None
    assert s.stats.clock_errors == 1


def test_several_misses_in_a_row_are() -> None:
    s = session_with(FlakyDevice([]))
    for _ in range(LOST_AFTER_FAILURES - 1):
        s._sample()
    assert s.lost_since is None
    s._sample()
    assert s.lost_since is not None and s.stats.lost == 1


def test_a_failing_port_is_lost_at_once() -> None:
    s = session_with(FlakyDevice([serial.SerialException("device reports readiness to read but returned no data")]))
    s._sample()
    assert s.lost_since is not None
