"""A live run's firings cost no memory over hours: the engine and its firing log keep the latest few in
memory (the recording keeps them all), counting every one; a demo that scores every firing keeps all."""

from __future__ import annotations

from flytrack_host.actuation.devices.base import Job, Outcome
from flytrack_host.actuation.engine import ALL_FIRES, RECENT_FIRES, ActuationEngine
from flytrack_host.actuation.firings import FiringLog
from flytrack_host.actuation.rules import Action, parse_rules


def _outcome(n: int) -> Outcome:
    job = Job("r", n, n, n + 1, 0.0, 0.0, (0.0, 0.0, 0.0), Action(output="valve"), False)
    return Outcome(job, "valve", "modbus", time_sent=1.0, time_ack=1.001, scheduled_frame=n + 1)


def test_the_firing_log_keeps_the_latest_and_counts_all() -> None:
    recorded: list[int] = []
    log = FiringLog(record=lambda row: recorded.append(int(row["obj_id"][0])), keep=5)
    for n in range(12):
        log.add(_outcome(n))
    assert log.count == 12 and recorded == list(range(12))  # every row reaches the recording
    assert log.table()["obj_id"].tolist() == list(range(7, 12))  # the memory holds the latest 5


def test_a_live_run_keeps_a_bounded_history() -> None:
    """The engine `flytrack run` builds (the default) bounds every per-firing list at RECENT_FIRES; the
    demo's scoring engine keeps them all."""
    box = {"inside": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}}
    rules = parse_rules({"rules": [{"name": "box", "dry_run": True, "when": box}]})
    live, scored = ActuationEngine(rules, [], 100.0), ActuationEngine(rules, [], 100.0, keep=ALL_FIRES)
    try:
        for eng, n in ((live, RECENT_FIRES), (scored, ALL_FIRES)):
            assert {eng.fires.maxlen, eng.shadow_fires.maxlen, eng.stages.maxlen, eng.sends.maxlen,
                    eng.firings.rows.maxlen} == {n}
        assert RECENT_FIRES <= 4096  # a day at 4 firings a second (~350 000) must not live in memory
    finally:
        live.close()
        scored.close()
