"""The OAK edge (flytrack_host.edges.oak): the real depthai pipeline object, and frames through the
`FrameSource` seam (real depthai.ImgFrame objects built on the host: there is no OAK device here) ->
the C extractor -> FEATURES over real UDP, compared datagram for datagram with flytrack-edge's on the
same frames; a device lost mid-stream; bad frames; the CLI."""

from __future__ import annotations

import datetime
import importlib.util
import threading
import time
from pathlib import Path

import depthai as dai
import numpy as np
import pytest

from flytrack_host.edges.oak.edge import ERR_BAD_FRAME, ERR_SOURCE, OakEdge, OakEdgeConfig, OakEdgeError
from flytrack_host.edges.oak.pipeline import STREAM, CameraSpec, OakConfigError, build_pipeline
from flytrack_host.edges.oak.source import BadFrame, DeviceLost, frame_from_imgframe
from flytrack_host.protocol import CameraState, EdgeStatus, FeatureFrame

# The frames of the C daemon's own tests (test_edge_daemon.py), loaded by path (importlib mode).
_spec = importlib.util.spec_from_file_location("_edge_daemon_tests", Path(__file__).with_name("test_edge_daemon.py"))
_daemon_tests = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_daemon_tests)
blob_frame, start_daemon, W, H = _daemon_tests.blob_frame, _daemon_tests.start, _daemon_tests.W, _daemon_tests.H

GRID = [(10 + 18 * (k % 8) + 0.3, 12 + 20 * (k // 8) + 0.6) for k in range(40)]  # > 32 points: SPLIT
TRUTH = [[], [(40.3, 50.7)], [(41.1, 51.2), (120.6, 30.4)], [(42.0, 52.0)], GRID, [(80.5, 60.2)]]


def img_frame(image: np.ndarray, seq: int, ts_us: int, kind=dai.ImgFrame.Type.GRAY8) -> dai.ImgFrame:
    """A frame as the device's XLink queue delivers it."""
    f = dai.ImgFrame()
    f.setData(np.ascontiguousarray(image).ravel())
    f.setWidth(image.shape[1])
    f.setHeight(image.shape[0])
    f.setType(kind)
    f.setSequenceNum(seq)
    f.setTimestampDevice(datetime.timedelta(microseconds=ts_us))
    return f


class ScriptedSource:
    """The device-link seam: plays a script of frames and failures. Each session is a list whose items
    are ImgFrames or a DeviceLost to raise; `opens` says which open() calls fail."""

    def __init__(self, sessions: list[list], open_fails: set[int] = frozenset()) -> None:
        self.sessions = sessions
        self.open_fails = open_fails
        self.opens = 0
        self.closes = 0
        self._items: list = []

    def open(self) -> None:
        n = self.opens
        self.opens += 1
        if n in self.open_fails:
            raise DeviceLost("X_LINK_DEVICE_NOT_FOUND (scripted)")
        self._items = list(self.sessions.pop(0)) if self.sessions else []

    def get(self, timeout: float):
        if not self._items:
            return None
        item = self._items.pop(0)
        if isinstance(item, Exception):
            raise item
        return item

    def close(self) -> None:
        self.closes += 1


def run_edge(source, receiver, max_frames: int, **kw) -> tuple[OakEdge, list]:
    delays: list[float] = []
    cfg = OakEdgeConfig(port=receiver.port, camera_index=3, width=W, height=H, max_frames=max_frames, **kw)
    edge = OakEdge(source, cfg, sleep=delays.append)
    try:
        edge.run()
    finally:
        edge.close()
    receiver.poll(0.3)
    return edge, delays


def features(msgs: list) -> list[FeatureFrame]:
    return [m for m in msgs if isinstance(m, FeatureFrame)]


def test_pipeline_is_built_from_real_depthai() -> None:
    j = build_pipeline(CameraSpec(kind="mono", socket="CAM_C", resolution="400p", fps=90.0)).serializeToJson()
    nodes = {nid: n for nid, n in j["pipeline"]["nodes"]}
    names = {n["name"]: nid for nid, n in nodes.items()}
    assert set(names) == {"MonoCamera", "XLinkOut"}
    cam = nodes[names["MonoCamera"]]["properties"]
    assert cam["fps"] == 90.0 and cam["boardSocket"] == int(dai.CameraBoardSocket.CAM_C)
    assert nodes[names["XLinkOut"]]["properties"]["streamName"] == STREAM
    links = [(c["node1Id"], c["node1Output"], c["node2Id"], c["node2Input"]) for c in j["pipeline"]["connections"]]
    assert links == [(names["MonoCamera"], "out", names["XLinkOut"], "in")]

    j = build_pipeline(CameraSpec(kind="color", socket="CAM_A", resolution="1080p")).serializeToJson()
    nodes = {n["name"]: nid for nid, n in j["pipeline"]["nodes"]}
    links = [(c["node1Id"], c["node1Output"], c["node2Id"]) for c in j["pipeline"]["connections"]]
    assert links == [(nodes["ColorCamera"], "video", nodes["XLinkOut"])]
    assert CameraSpec(kind="color", resolution="1080p").size() == (1920, 1080)
    for bad in (CameraSpec(kind="stereo"), CameraSpec(resolution="4k"), CameraSpec(socket="CAM_Z"),
                CameraSpec(fps=float("nan"))):
        with pytest.raises(OakConfigError):
            build_pipeline(bad)


def test_imgframe_luma_sequence_and_device_clock() -> None:
    img = blob_frame([(40.3, 50.7)])
    f = frame_from_imgframe(img_frame(img, 17, 12_345_678))
    assert f.sequence_num == 17 and f.device_timestamp_ns == 12_345_678_000
    assert np.array_equal(f.image, img)
    # NV12: the Y plane first, then interleaved chroma at half size; only the luma is used.
    nv12 = np.concatenate([img.ravel(), np.full(W * H // 2, 128, np.uint8)])
    f = dai.ImgFrame()
    f.setData(nv12), f.setWidth(W), f.setHeight(H), f.setType(dai.ImgFrame.Type.NV12)
    assert np.array_equal(frame_from_imgframe(f).image, img)
    with pytest.raises(BadFrame, match="RGB888i"):
        frame_from_imgframe(img_frame(img, 1, 0, dai.ImgFrame.Type.RGB888i))
    short = dai.ImgFrame()
    short.setData(img.ravel()[:100]), short.setWidth(W), short.setHeight(H), short.setType(dai.ImgFrame.Type.GRAY8)
    with pytest.raises(BadFrame, match="100 bytes"):
        frame_from_imgframe(short)


def test_same_features_datagrams_as_the_c_daemon(edge_bin: Path, receiver) -> None:
    frames = [blob_frame(b) for b in TRUTH]
    # The C daemon on these frames (raw stdin).
    p, _ = start_daemon(edge_bin, receiver, "--source", "raw", "--input", "-", "--width", str(W),
                        "--height", str(H), "--camera-index", "3")
    p.stdin.write(b"".join(f.tobytes() for f in frames))
    p.stdin.close()
    assert p.wait(10) == 0, p.stderr.read().decode()
    receiver.poll(0.3)
    c_parts = features(receiver.messages)
    receiver.messages.clear()
    # The OAK edge on the same frames, with device sequence numbers from 1000 and a 10 ms device clock.
    src = ScriptedSource([[img_frame(f, 1000 + i, 5_000_000 + 10_000 * i) for i, f in enumerate(frames)]])
    edge, _ = run_edge(src, receiver, max_frames=len(frames))
    oak_parts = features(receiver.messages)
    key = lambda m: (m.camera_frame, m.part_index)  # noqa: E731
    c_parts.sort(key=key)
    oak_parts.sort(key=key)
    assert len(c_parts) == len(oak_parts) == len(frames) + 1  # the 40-blob frame is SPLIT in 2
    for c, o in zip(c_parts, oak_parts, strict=True):
        assert o.camera_frame == 1000 + c.camera_frame
        assert o.device_timestamp_ns == 5_000_000_000 + 10_000_000 * c.camera_frame
        assert (o.camera_index, o.n_points, o.total_points, o.part_index, o.part_count, o.flags) == \
               (c.camera_index, c.n_points, c.total_points, c.part_index, c.part_count, c.flags)
        assert o.points.tobytes() == c.points.tobytes()  # bit for bit: the same C code on the same pixels
        assert o.trigger_frame == -1 and o.edge_recv_ns <= o.edge_done_ns
    assert sum(m.n_points for m in oak_parts) == sum(len(b) for b in TRUTH)
    seqs = [m.seq for m in receiver.messages]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    st = [m for m in receiver.messages if isinstance(m, EdgeStatus)]
    assert st[0].state == CameraState.RUNNING and st[-1].state == CameraState.STOPPED
    assert st[-1].frames_seen == len(frames) and st[-1].frames_dropped == 0
    assert (st[-1].width, st[-1].height, st[-1].camera_index, st[-1].camera_name) == (W, H, 3, "oak")


def test_device_lost_mid_stream_reports_and_reconnects(receiver) -> None:
    frames = [blob_frame(b) for b in TRUTH[:4]]
    lost = DeviceLost("Communication exception - Couldn't read data from stream (X_LINK_ERROR)")
    # Session 1: frames 0-2 (device seq 0, 1, 3: one dropped on the device), then the device vanishes;
    # the first reconnect fails, the second gets a freshly booted device counting from 0 again.
    s1 = [img_frame(frames[0], 0, 0), img_frame(frames[1], 1, 10_000), img_frame(frames[2], 3, 30_000), lost]
    s2 = [img_frame(frames[3], 0, 500), img_frame(frames[1], 1, 10_500)]
    src = ScriptedSource([s1, s2], open_fails={1})
    edge, delays = run_edge(src, receiver, max_frames=5, reconnect_delay=0.5)
    assert src.opens == 3 and edge.reconnects == 1 and delays == [0.5, 0.5]
    fr = features(receiver.messages)
    assert [m.camera_frame for m in fr] == [0, 1, 3, 4, 5]  # still increasing after the reconnect
    assert edge.frames_dropped == 1
    st = [m for m in receiver.messages if isinstance(m, EdgeStatus)]
    errors = [m for m in st if m.state == CameraState.ERROR]
    assert errors and errors[0].last_error_code == ERR_SOURCE
    assert "OAK device lost after frame 3" in errors[0].last_error
    # The ERROR status went out before any frame of the new session.
    first_new = next(m.seq for m in fr if m.camera_frame == 4)
    assert errors[0].seq < first_new and errors[0].frames_seen == 3
    assert st[-1].state == CameraState.STOPPED and st[-1].last_error_code == 0 and st[-1].frames_seen == 5


def test_device_gone_for_good_is_a_clear_error(receiver) -> None:
    src = ScriptedSource([[img_frame(blob_frame([]), 0, 0), DeviceLost("X_LINK_ERROR")]], open_fails={1, 2, 3})
    with pytest.raises(OakEdgeError, match="not available after 3 attempts"):
        run_edge(src, receiver, max_frames=10, reconnect_tries=2)
    receiver.poll(0.3)
    st = [m for m in receiver.messages if isinstance(m, EdgeStatus)]
    assert st[-1].state == CameraState.ERROR and st[-1].last_error_code == ERR_SOURCE
    assert st[-1].frames_seen == 1 and src.closes >= 1


def test_bad_frames_are_counted_not_processed(receiver) -> None:
    good = blob_frame([])
    src = ScriptedSource([[img_frame(good, 0, 0), img_frame(np.zeros((H, W + 2), np.uint8), 1, 10),
                           img_frame(good, 2, 20, dai.ImgFrame.Type.RGB888i), img_frame(good, 3, 30)]])
    edge, _ = run_edge(src, receiver, max_frames=4)
    assert [m.camera_frame for m in features(receiver.messages)] == [0, 3]
    st = [m for m in receiver.messages if isinstance(m, EdgeStatus)][-1]
    assert st.frames_seen == 2 and st.frames_dropped == 2 and st.last_error_code == ERR_BAD_FRAME
    assert "RGB888i" in st.last_error


def _flytrack(*args: str):
    from typer.testing import CliRunner

    from flytrack_host.cli import app

    return CliRunner().invoke(app, list(args))


def test_cli_help_and_no_device() -> None:
    out = _flytrack("edge-oak", "--help")
    assert out.exit_code == 0, out.output
    for opt in ("--host", "--port", "--camera-index", "--device", "--socket", "--resolution", "--fps",
                "--diff-threshold", "--reconnect-tries"):
        assert opt in out.stdout
    out = _flytrack("edge-oak", "--port", "9")
    assert out.exit_code == 2, out.output
    assert "no OAK device" in out.stderr and "Traceback" not in out.output
    out = _flytrack("edge-oak", "--resolution", "4k")
    assert out.exit_code == 2 and "resolution '4k'" in out.stderr


class EndlessSource(ScriptedSource):
    """Frames at about 200 fps for as long as asked (a camera that keeps streaming)."""

    def __init__(self) -> None:
        super().__init__([])
        self.n = 0
        self.image = blob_frame([(40.3, 50.7)])
        self.blank = blob_frame([])

    def get(self, timeout: float):
        time.sleep(0.005)
        self.n += 1
        # Frame 0 (the background) is empty, then one fly.
        return img_frame(self.image if self.n > 1 else self.blank, self.n - 1, 5000 * (self.n - 1))


def test_live_heartbeat_and_stop_from_another_thread(receiver) -> None:
    src = EndlessSource()
    cfg = OakEdgeConfig(port=receiver.port, camera_index=1, width=W, height=H, status_interval=0.1)
    edge = OakEdge(src, cfg)
    t = threading.Thread(target=edge.run, daemon=True)
    t.start()
    try:
        running = receiver.wait_for(lambda m: isinstance(m, EdgeStatus) and m.state == CameraState.RUNNING
                                    and m.frames_seen >= 20, 20.0)
        assert running, "no heartbeat with 20 frames seen"
        # The heartbeat keeps coming while frames flow (every 0.1 s here).
        beats = receiver.wait_for(lambda m: isinstance(m, EdgeStatus) and m.frames_seen >= running[0].frames_seen
                                  + 5 and m.seq > running[0].seq, 20.0)
        assert beats, "the heartbeat stopped"
    finally:
        edge.stop()
        t.join(10)
    assert not t.is_alive()
    edge.close()
    receiver.poll(0.3)
    st = [m for m in receiver.messages if isinstance(m, EdgeStatus)]
    assert st[-1].state == CameraState.STOPPED
    fr = features(receiver.messages)
    assert st[-1].frames_seen == len(fr) == src.n  # every frame read was sent, none lost on loopback
    assert [m.camera_frame for m in fr] == list(range(len(fr)))
    assert all(m.n_points == 1 for m in fr[1:150])  # (before the first background update at 200)


class PacedSource(ScriptedSource):
    def get(self, timeout: float):
        time.sleep(0.01)  # about 100 fps, the rig's trigger rate
        return super().get(timeout)


def test_host_pipeline_records_the_oak_points(tmp_path: Path) -> None:
    """A real HostPipeline receives the OAK edge's datagrams: its recording holds every point the C
    extractor finds on these frames, under the device's frame numbers and clock."""
    from flytrack_host.edges.features.extractor import FeatureExtractor
    from flytrack_host.pipeline import HostPipeline
    from flytrack_host.recording import load_recording
    from flytrack_host.rig import parse_rig

    rig = parse_rig({"name": "oakrig", "trigger": {"kind": "software", "fps": 100.0},
                     "host": {"listen": "127.0.0.1:7000"}, "recording": {"folder": str(tmp_path)},
                     "cameras": [{"name": "oak0", "index": 0, "edge": "127.0.0.1"}]})
    pipe = HostPipeline(rig, cameras={0: None}, tracker_factory=None, recording_path=tmp_path / "r",
                        bind="127.0.0.1:0")
    pipe.start()
    frames = [blob_frame(b) for b in TRUTH]
    src = PacedSource([[img_frame(f, 50 + i, 1000 * i) for i, f in enumerate(frames)]])
    host, port = pipe.address
    edge = OakEdge(src, OakEdgeConfig(host=host, port=port, camera_index=0, width=W, height=H,
                                      max_frames=len(frames)))
    try:
        edge.run()
    finally:
        edge.close()
        time.sleep(0.2)
        summary = pipe.stop()
    cam = summary["receiver"]["cameras"][0]
    assert cam["frames"] == len(frames) and cam["lost"] == 0 and cam["malformed"] == 0, cam
    d2 = load_recording(summary["recording"]).table("data2d_distorted")
    d2 = d2[np.isfinite(d2["x_dist"])]
    with FeatureExtractor(W, H) as fx:
        want = [(50 + i, p) for i, f in enumerate(frames) for p in fx.process(f).points]
    assert len(d2) == len(want) == sum(len(b) for b in TRUTH)
    for row, (frame, p) in zip(d2, want, strict=True):
        assert row["camera_frame"] == frame and row["device_timestamp_ns"] == 1_000_000 * (frame - 50)
        for k in ("x_dist", "y_dist", "x_undist", "y_undist", "area", "peak_diff"):
            assert row[k] == np.float32(p[k]), k
