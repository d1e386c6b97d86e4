"""Hostile and faulty input over real UDP: no datagram, bundle or tracker failure ends the tracking
thread, and every good frame after it is still tracked and recorded (GitHub issue 5, A1 and A8)."""

from __future__ import annotations

import time

import numpy as np

from flytrack_host.intake.receiver import Receiver
from flytrack_host.intake.sync import CameraFrame
from flytrack_host.pipeline import HostPipeline
from flytrack_host.protocol import FeatureFlags, FeatureFrame, encode
from flytrack_host.recording import load_recording

ADDR = ("127.0.0.1", 5555)


def _part(edge, frame: int, index: int, count: int, helpers) -> bytes:
    """One SPLIT datagram of camera frame `frame` claiming to be part `index` of `count`."""
    ff = FeatureFrame(camera_index=edge.cam, seq=edge.seq, camera_frame=frame, trigger_frame=frame,
                      total_points=32 * count, part_index=index, part_count=count,
                      flags=int(FeatureFlags.SPLIT), points=helpers.points_for(edge.cam, frame, 2))
    edge.seq += 1
    return encode(ff)


def _pace(t0: float, k: int, fps: float) -> None:
    sleep = t0 + (k + 1) / fps - time.monotonic()
    if sleep > 0:
        time.sleep(sleep)


def test_parts_disagreeing_on_part_count_are_kept_apart(helpers):
    """Part 2 of 3 then part 1 of 2 of the same camera frame: before the fix the second made the
    receiver join {1, 2} as a complete 2-part frame (KeyError on part 0)."""
    rx = Receiver(helpers.make_rig(1), bind="127.0.0.1:0", split_timeout_s=0.01)
    try:
        e = helpers.EdgeSim(0, ("127.0.0.1", 1))
        out: list = []
        rx.handle(_part(e, 5, 2, 3, helpers), ADDR, 1.0, out)
        rx.handle(_part(e, 5, 1, 2, helpers), ADDR, 1.0, out)
        assert out == []
        rx.handle(_part(e, 5, 0, 2, helpers), ADDR, 1.0, out)  # completes the 2-part frame
        assert len(out) == 1 and isinstance(out[0], CameraFrame) and not out[0].incomplete
        assert len(out[0].points) == 4
        time.sleep(0.02)
        rx.expire(time.monotonic(), out)  # the lone part of 3 is passed on, flagged
        assert len(out) == 2 and out[1].incomplete
        assert rx.stats.cameras[0].split_incomplete == 1
    finally:
        rx.close()


def test_hostile_split_sequence_does_not_stop_the_host(helpers, tmp_path):
    fps = 200.0
    rig = helpers.make_rig(2, fps=fps)
    pipe = HostPipeline(rig, cameras={0: None, 1: None}, tracker_factory=helpers.factory,
                        recording_path=tmp_path / "r", bind="127.0.0.1:0", keep_results=True)
    pipe.start()
    e0 = helpers.EdgeSim(0, pipe.address, edge_trigger=True)
    e1 = helpers.EdgeSim(1, pipe.address, edge_trigger=True)
    alive_after_attack = False
    try:
        t0 = time.monotonic()
        for k in range(80):
            e1.send(k)
            if k == 20:
                e0.raw(_part(e0, k, 2, 3, helpers))
                e0.raw(_part(e0, k, 1, 2, helpers))
            else:
                e0.send(k)
            if k == 40:
                alive_after_attack = pipe.running
            _pace(t0, k, fps)
        time.sleep(0.1)
        alive_at_end = pipe.running
    finally:
        summary = pipe.stop()  # raised "tracking thread failed" before the fix
    assert alive_after_attack and alive_at_end
    tracked = [r.trigger_frame for r in pipe.results]
    assert set(range(21, 80)) <= set(tracked), sorted(set(range(21, 80)) - set(tracked))
    rec = load_recording(summary["recording"])
    d2 = rec.table("data2d_distorted")
    for cam in (0, 1):
        frames = set(d2[d2["camera_index"] == cam]["camera_frame"].tolist())
        assert set(range(80)) <= frames, (cam, sorted(set(range(80)) - frames))
    # The two hostile parts are kept too, each as an incomplete split frame.
    bad = d2[(d2["camera_index"] == 0) & (d2["camera_frame"] == 20)]
    assert len(bad) == 4 and np.all(bad["flags"] & 8)
    assert summary["receiver"]["cameras"][0]["split_incomplete"] == 2


class _RaisingSync:
    """Wraps the real synchroniser; `add` raises for one camera frame (a bug on one datagram)."""

    def __init__(self, sync, bad_frame: int):
        self._sync = sync
        self._bad = bad_frame

    def add(self, frame, now):
        if frame.camera_index == 0 and frame.camera_frame == self._bad:
            raise ValueError("synchroniser bug on this frame")
        return self._sync.add(frame, now)

    def __getattr__(self, name):
        return getattr(self._sync, name)


def test_an_exception_on_one_item_is_counted_and_the_frame_still_recorded(helpers, tmp_path):
    fps = 200.0
    pipe = HostPipeline(helpers.make_rig(2, fps=fps), cameras={0: None, 1: None}, tracker_factory=helpers.factory,
                        recording_path=tmp_path / "r", bind="127.0.0.1:0", keep_results=True)
    pipe.start()
    pipe.sync = _RaisingSync(pipe.sync, bad_frame=15)
    edges = [helpers.EdgeSim(i, pipe.address, edge_trigger=True) for i in range(2)]
    try:
        t0 = time.monotonic()
        for k in range(40):
            for e in edges:
                e.send(k)
            _pace(t0, k, fps)
        time.sleep(0.1)
    finally:
        summary = pipe.stop()
    assert summary["loop_errors"] == 1
    assert set(range(16, 40)) <= {r.trigger_frame for r in pipe.results}
    rec = load_recording(summary["recording"])
    d2 = rec.table("data2d_distorted")
    assert set(d2[d2["camera_index"] == 0]["camera_frame"].tolist()) == set(range(40))
    assert any("synchroniser bug" in r["message"] for r in rec.textlog)


class _PoisonedTracker:
    """Raises on one frame and is left broken, as a tracker half-updated by an exception would be:
    every later frame of the same instance fails too."""

    instances = 0

    def __init__(self, inner):
        _PoisonedTracker.instances += 1
        self.inner = inner
        self.broken = False

    def process(self, bundle):
        if self.broken:
            raise RuntimeError("tracker state corrupted")
        if bundle.trigger_frame == 10 and _PoisonedTracker.instances == 1:
            self.broken = True
            raise RuntimeError("tracker bug on frame 10")
        return self.inner.process(bundle)


def test_a_tracker_exception_rebuilds_the_tracker(helpers, tmp_path):
    fps = 200.0
    _PoisonedTracker.instances = 0

    def factory(cameras, params, period):
        return _PoisonedTracker(helpers.factory(cameras, params, period))

    pipe = HostPipeline(helpers.make_rig(2, fps=fps), cameras={0: None, 1: None}, tracker_factory=factory,
                        recording_path=tmp_path / "r", bind="127.0.0.1:0", keep_results=True)
    pipe.start()
    edges = [helpers.EdgeSim(i, pipe.address, edge_trigger=True) for i in range(2)]
    try:
        t0 = time.monotonic()
        for k in range(40):
            for e in edges:
                e.send(k)
            _pace(t0, k, fps)
        time.sleep(0.1)
        status = pipe.status_line()
    finally:
        summary = pipe.stop()
    assert summary["tracker_errors"] == 1 and summary["tracker_resets"] == 1
    assert _PoisonedTracker.instances == 2
    assert [r.trigger_frame for r in pipe.results] == [k for k in range(40) if k != 10]
    assert "tracker errors 1" in status
    rec = load_recording(summary["recording"])
    assert any("tracker bug on frame 10" in r["message"] and "restarted" in r["message"] for r in rec.textlog)
    d2 = rec.table("data2d_distorted")
    assert set(d2["trigger_frame"].tolist()) == set(range(40))  # frame 10's 2D data recorded too
