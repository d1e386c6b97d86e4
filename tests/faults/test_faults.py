"""The fault-injection suite (`make test-faults`) as tests: each fault of issue 16, and each that
already held, against the simulated rig's real processes (flytrack-edge, simavr or the software
trigger, loopback UDP, the host), with the goals: nothing recorded is lost, the numbering is right
again within 1 s of the fault's end, the fault is named in the log (once, then with a count), and
the figure that went wrong before is right now."""

from __future__ import annotations

import math

import pytest

from flytrack_host.sim.faults.suite import SCENARIOS, format_table, run_suite
from flytrack_host.sim.run import find_edge_binary


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    try:
        find_edge_binary()
    except Exception as exc:
        pytest.fail(f"{exc}")
    got = run_suite(jobs=3, root=tmp_path_factory.mktemp("faults"))
    print("\n" + format_table(got))
    return {r["name"]: r for r in got}


def _row(rows, name):
    r = rows[name]
    if "skipped" in r:
        pytest.skip(r["skipped"])
    assert "error" not in r, r["error"]
    assert r["fault_error"] is None, r["fault_error"]
    return r


def _log_lines_bound(r) -> int:
    """Lines a fault may take in the log: per kind of message the first at once, then one with a count
    every 5 s while it goes on, and the counts at stop (ratelog.py). The kinds a flood names are its
    error names (BAD_MAGIC, ...) and the unknown camera; every other fault is one kind. Measured at
    most 6 on an idle machine; a loaded one stretches the run (7 lines at load 13 in a 6 s flood run),
    so the bound follows the run's own wall time."""
    rx = r.get("receiver") or {}
    kinds = max(1, len(rx.get("errors_by_name") or {}) + (1 if rx.get("rejected_camera") else 0))
    return max(6, kinds * (2 + math.ceil(float(r.get("wall_s") or 0.0) / 5.0)))


@pytest.mark.slow
@pytest.mark.parametrize("name", [s.name for s in SCENARIOS])
def test_fault_loses_nothing_and_numbering_is_right_within_a_second(rows, name):
    r = _row(rows, name)
    sc = next(s for s in SCENARIOS if s.name == name)
    if not sc.lost_ok:
        assert r["frames_lost"] == 0, r
    assert r["recovery_s"] <= 1.0, r
    # A restarted edge's frames wait until it caught up and are placed then: none misnumbered (at
    # load 10-15, 0 in 6 runs; before, 20-171 while the host waited for its frames to come paced).
    assert r["frames_misnumbered"] <= 5, r  # measured 0 for every fault
    assert r["rogue_tracked"] == 0, r
    if name == "none":
        assert r["mota"] > 0.95 and r["frames_misnumbered"] == 0
        return
    # Named in the log: the first line at once, then at most a count now and then.
    assert 1 <= r["message_count"] <= _log_lines_bound(r), (r["message"], r["message_count"], r.get("wall_s"))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["wall-1", "wall-30", "wall+3600", "wall-1-fixed"])
def test_wall_clock_steps_change_no_timing(rows, name):
    r = _row(rows, name)
    assert r["host"]["wall_clock_steps"] == 1
    assert r["frames_misnumbered"] == 0, r
    # Before: a +1 h step reported 3,600,026 ms; with --no-trigger tracking froze. The least arrival
    # lag (trigger -> frame) of the 100 frames after the step against the 100 before moves by less
    # than half the step (a step moves every frame by it). The run's own floor is the reference: a
    # loaded machine delays the simulated cameras by 0.3-0.9 s (P50 773 ms at load 11 failed a fixed
    # 200 ms bound; medians moved by 875 ms across a -1 s step at load 13).
    step_ms = abs(float(name.removeprefix("wall").removesuffix("-fixed"))) * 1e3
    d = r["arrival_floor_step_ms"]
    assert d is not None and abs(d) < 0.5 * step_ms, (d, r["latency_p50_ms"], r["latency_p99_ms"])


@pytest.mark.slow
def test_a_misnumbering_edge_is_rejected_frame_by_frame(rows):
    r = _row(rows, "misnumber")
    assert r["rogue_recorded"] >= 10 and r["rogue_tracked"] == 0
    assert r["sync_cam1"]["early"] == r["rogue_recorded"] // 2  # two points: two rows per frame
    rx = r["receiver_cam1"]
    assert rx["lost"] == 0 and rx["restarts"] == 0  # the interleaved numbering is no loss, no restart
    assert r["host"]["range_errors"] == 0


@pytest.mark.slow
def test_a_second_edge_for_a_camera_in_use_is_rejected_and_counted(rows):
    r = _row(rows, "second-edge")
    assert r["receiver_cam1"]["second_sender"] >= 20
    assert r["frames_misnumbered"] == 0


@pytest.mark.slow
def test_an_edge_restart_is_a_restart_and_its_gap_is_counted(rows):
    r = _row(rows, "restart")
    rx, sy = r["receiver_cam1"], r["sync_cam1"]
    assert rx["restarts"] == 1 and rx["reordered"] == 0
    assert sy["restarts"] == 1
    down = r["fault_info"]["pulses_while_down"]
    # Lost: the frames rendered while the edge was down, and those still in the killed edge's pipe
    # (up to 13 frames of 320 x 240 in a 1 MB pipe), nothing more.
    assert down <= r["frames_lost"] <= down + 16, (r["frames_lost"], down)
    # The host counts them from the trigger: placed by arrival, a loaded host may be a few frames off.
    assert abs(sy["missed"] - r["frames_lost"]) <= max(3, 0.1 * down), (sy["missed"], r["frames_lost"])


@pytest.mark.slow
def test_a_flood_is_counted_and_logged_with_counts(rows):
    r = _row(rows, "flood")
    rx = r["receiver"]
    assert rx["internal_errors"] == 0
    # Every datagram that reached the host is counted (the kernel may drop some of a flood on a busy
    # machine: the edges' own datagrams lost that way show in the receiver's loss count).
    assert sum(rx["errors_by_name"].values()) + rx["rejected_camera"] >= 10_000
    assert r["frames_lost"] <= r["receiver_lost"], (r["frames_lost"], r["receiver_lost"])
    assert r["message_count"] <= _log_lines_bound(r), (r["message_count"], r.get("wall_s"))


@pytest.mark.slow
def test_a_stalled_host_catches_up_and_says_so(rows):
    r = _row(rows, "host-stop")
    assert r["host"]["stalls"] >= 1 and r["host"]["behind_skipped"] >= 1
    # Bounded backlog: no frame tracked after waiting in the host longer than the bound (1 s) plus a
    # loaded host's jitter.
    assert r["host_delay_after_p99_ms"] is not None and r["host_delay_after_p99_ms"] < 1300


@pytest.mark.slow
def test_fixed_rate_clock_is_reanchored_after_a_pause(rows):
    r = _row(rows, "trigger-pause")
    # Before: every frame after a 0.5 s pause reported ~508 ms (the median too). The least arrival lag
    # after it holds no part of the pause: under half of it (a loaded machine delays frames, not all of
    # them: after-pause P50 334 ms at load 12 failed a fixed 150 ms bound on the median).
    assert r["latency_after_p50_ms"] is not None
    assert r["arrival_after_min_ms"] is not None and r["arrival_after_min_ms"] < 250, r["arrival_after_min_ms"]
    assert r["frames_misnumbered"] == 0



@pytest.mark.slow
def test_a_killed_host_is_recovered_up_to_its_last_second(rows):
    r = _row(rows, "host-kill")
    assert r["recover_exit"] == 0, r["message"]
    assert r["frames_recovered"] >= 150  # 2 s at 100 fps, 3 cameras, on a busy machine
    assert r["frames_lost"] == 0  # no hole in any camera's frames up to the kill
    assert r["last_row_before_kill_s"] < 1.0  # recoverable up to its last second
