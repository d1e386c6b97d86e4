"""The demo's CPU split: the host process on its CPUs, every thread of a simulated hardware process on
the others, and the host's own CPUs given back when the run ends (tests run the demo in-process)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest

from flytrack_host.util.placement import Placement, run_as_hardware, split_cpus, threads_of, to_hardware


def test_split_gives_the_host_the_first_half_and_the_hardware_the_rest():
    assert split_cpus({0, 1}) == split_cpus(frozenset({1, 0}))
    s = split_cpus({0, 1})
    assert s is not None and (s.host, s.hardware) == ({0}, {1})
    s = split_cpus({0, 1, 2, 3})
    assert s is not None and (s.host, s.hardware) == ({0, 1}, {2, 3})
    s = split_cpus({0, 2, 4})  # what a cgroup or taskset left: the CPUs as given, not 0..n-1
    assert s is not None and (s.host, s.hardware) == ({0}, {2, 4})
    assert split_cpus({3}) is None  # one CPU: nothing to split


def _child() -> subprocess.Popen:
    # A process with a second thread already running when it is placed (as the Modbus server is).
    code = ("import threading, time; threading.Thread(target=time.sleep, args=(30,), daemon=True).start(); "
            "time.sleep(30)")
    p = subprocess.Popen([sys.executable, "-c", code])
    for _ in range(200):
        if len(threads_of(p.pid)) >= 2:
            break
        threading.Event().wait(0.01)
    return p


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to split")
def test_placement_puts_host_and_hardware_threads_apart_and_gives_the_cpus_back():
    before = os.sched_getaffinity(0)
    child = _child()
    try:
        with Placement(split=True) as p:
            assert p.split is not None
            d = p.describe()
            assert d is not None and set(d["host"]) | set(d["simulated_hardware"]) == before
            assert not set(d["host"]) & set(d["simulated_hardware"])
            # Every thread of this process, and a thread started now, on the host's CPUs.
            for tid in threads_of(0):
                assert os.sched_getaffinity(tid) == p.split.host
            seen: list[set[int]] = []
            t = threading.Thread(target=lambda: seen.append(os.sched_getaffinity(0)))
            t.start()
            t.join()
            assert seen == [set(p.split.host)]
            # Every thread of a simulated hardware process on the hardware's CPUs.
            assert len(threads_of(child.pid)) >= 2
            run_as_hardware(child.pid)
            for tid in threads_of(child.pid):
                assert os.sched_getaffinity(tid) == p.split.hardware
        # Given back: this process as before; nothing placed any more.
        for tid in threads_of(0):
            assert os.sched_getaffinity(tid) == before
        assert to_hardware(child.pid) is False
    finally:
        child.kill()
        child.wait()


def test_shared_cpus_place_nothing():
    before = os.sched_getaffinity(0)
    with Placement(split=False) as p:
        assert p.describe() is None
        assert os.sched_getaffinity(0) == before
        assert to_hardware(os.getpid()) is False
    assert os.sched_getaffinity(0) == before


def test_a_process_that_is_gone_is_not_an_error():
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    with Placement(split=True):
        assert run_as_hardware(p.pid) is False  # gone: nothing placed, no priority raised


def test_auto_splits_unless_the_cameras_need_more_than_their_half():
    from flytrack_host.util.placement import FRAMES_PER_HARDWARE_CPU, choose_split

    assert choose_split("auto", 5 * 100, {0, 1}) == (True, "")  # the default demo
    split, why = choose_split("auto", 11 * 200, {0, 1})  # make demo-stress: the cameras need the machine
    assert not split and "2200 camera frames/s" in why
    assert choose_split("auto", 11 * 200, set(range(8)))[0]  # 4 hardware CPUs: room
    assert choose_split("auto", FRAMES_PER_HARDWARE_CPU, {0, 1})[0]
    assert choose_split("auto", 100, {0}) == (False, "")  # one CPU: nothing to split, nothing to say
    assert choose_split("split", 1e6, {0, 1}) == (True, "")
    assert choose_split("share", 10, {0, 1}) == (False, "")
