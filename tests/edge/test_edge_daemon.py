"""flytrack-edge end to end: real process, real UDP on loopback, frames through stdin/files/Y4M, the
host's Python codec decoding every datagram; control messages; bad input."""

from __future__ import annotations

import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.protocol import (
    AckStatus,
    Command,
    Control,
    ControlAck,
    EdgeStatus,
    FeatureFrame,
    ImageChunk,
    encode,
)

W, H = 160, 120


def blob_frame(blobs: list[tuple[float, float]], w: int = W, h: int = H, bg: int = 20) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.full((h, w), float(bg))
    for x, y in blobs:
        img += 180.0 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.8**2))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def free_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def start(edge_bin: Path, receiver, *args: str, stdin=subprocess.PIPE) -> tuple[subprocess.Popen, int]:
    cport = free_port()
    cmd = [str(edge_bin), "--host", "127.0.0.1", "--port", str(receiver.port), "--control-port",
           str(cport), "--bind", "127.0.0.1", *args]
    p = subprocess.Popen(cmd, stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    return p, cport


def features(msgs: list) -> list[FeatureFrame]:
    return [m for m in msgs if isinstance(m, FeatureFrame)]


def test_help_explains_every_option(edge_bin: Path) -> None:
    out = subprocess.run([str(edge_bin), "--help"], capture_output=True, text=True, timeout=10)
    assert out.returncode == 0
    for opt in ("--source", "--input", "--width", "--pixel-format", "--host", "--control-port",
                "--diff-threshold", "--n-sigma", "--alpha", "--bg-update-interval", "--truncate",
                "--config", "--intrinsics", "--distortion", "--mask", "--regions"):
        assert opt in out.stdout


def test_stdin_stream_one_features_datagram_per_frame(edge_bin: Path, receiver) -> None:
    p, _ = start(edge_bin, receiver, "--source", "raw", "--input", "-", "--width", str(W),
                 "--height", str(H), "--camera-index", "3")
    truth = [[], [(40.3, 50.7)], [(41.1, 51.2), (120.6, 30.4)], [(42.0, 52.0)]]
    # Low latency: each frame's FEATURES must arrive while the next frame has not been written yet.
    for i, blobs in enumerate(truth):
        p.stdin.write(blob_frame(blobs).tobytes())
        p.stdin.flush()
        got = receiver.wait_for(lambda m, i=i: isinstance(m, FeatureFrame) and m.camera_frame == i, 5.0)
        assert got, f"no FEATURES for frame {i} before the next frame was written"
    p.stdin.close()
    assert p.wait(10) == 0, p.stderr.read().decode()
    receiver.poll(0.2)
    fr = sorted(features(receiver.messages), key=lambda m: m.camera_frame)
    assert [m.camera_frame for m in fr] == [0, 1, 2, 3]
    assert all(m.camera_index == 3 and m.part_count == 1 and m.trigger_frame == -1 for m in fr)
    assert all(m.edge_recv_ns <= m.edge_done_ns for m in fr)
    for m, blobs in zip(fr[1:], truth[1:], strict=True):
        assert m.n_points == len(blobs) == m.total_points
        for x, y in blobs:
            d = np.hypot(m.points["x_dist"] - x, m.points["y_dist"] - y).min()
            assert d < 0.06
    assert fr[0].n_points == 0  # the first frame is the background
    seqs = [m.seq for m in receiver.messages if hasattr(m, "seq")]
    assert seqs == sorted(seqs)
    statuses = [m for m in receiver.messages if isinstance(m, EdgeStatus)]
    assert statuses and statuses[-1].frames_seen == 4 and statuses[-1].width == W


def test_y4m_file_and_split_and_truncate(edge_bin: Path, receiver, tmp_path: Path) -> None:
    # 40 blobs in one frame: more than 32 points.
    grid = [(10 + 18 * (k % 8) + 0.3, 12 + 20 * (k // 8) + 0.6) for k in range(40)]
    frames = [blob_frame([], 160, 120), blob_frame(grid, 160, 120)]
    y4m = tmp_path / "in.y4m"
    with open(y4m, "wb") as fh:
        fh.write(b"YUV4MPEG2 W160 H120 F100:1 Ip A1:1 C420jpeg\n")
        for f in frames:
            fh.write(b"FRAME\n" + f.tobytes() + bytes(2 * 80 * 60))
    p, _ = start(edge_bin, receiver, "--source", "y4m", "--input", str(y4m), stdin=subprocess.DEVNULL)
    assert p.wait(10) == 0, p.stderr.read().decode()
    receiver.poll(0.3)
    parts = [m for m in features(receiver.messages) if m.camera_frame == 1]
    assert len(parts) == 2 and all(m.split for m in parts)
    assert sorted(m.part_index for m in parts) == [0, 1] and {m.part_count for m in parts} == {2}
    assert sum(m.n_points for m in parts) == 40 and {m.total_points for m in parts} == {40}
    receiver.messages.clear()
    p, _ = start(edge_bin, receiver, "--source", "y4m", "--input", str(y4m), "--truncate", "1",
                 stdin=subprocess.DEVNULL)
    assert p.wait(10) == 0
    receiver.poll(0.3)
    parts = [m for m in features(receiver.messages) if m.camera_frame == 1]
    assert len(parts) == 1 and parts[0].truncated and not parts[0].split
    assert parts[0].n_points == 32 and parts[0].total_points == 40


def ctl(receiver, cport: int, rid: int, cmd: Command, param: str = "", value: float = 0.0) -> ControlAck:
    receiver.send(encode(Control(request_id=rid, camera_index=0xFFFF, command=int(cmd), param=param,
                                 value=value)), cport)
    acks = receiver.wait_for(lambda m: isinstance(m, ControlAck) and m.request_id == rid, 5.0)
    assert acks, f"no CONTROL_ACK for request {rid}"
    return acks[0]


def test_control_messages(edge_bin: Path, receiver) -> None:
    p, cport = start(edge_bin, receiver, "--width", str(W), "--height", str(H), "--start-stopped", "1")
    try:
        bg = blob_frame([])
        one = blob_frame([(60.4, 70.2)])
        # The first STATUS says the daemon is up and listening (a CONTROL sent earlier would be lost).
        assert receiver.wait_for(lambda m: isinstance(m, EdgeStatus), 10.0)
        a = ctl(receiver, cport, 1, Command.SET_PARAM, "diff_threshold", 25.0)
        assert a.status == AckStatus.OK
        assert ctl(receiver, cport, 2, Command.SET_PARAM, "no_such_thing", 1).status == AckStatus.UNKNOWN_PARAM
        assert ctl(receiver, cport, 3, Command.SET_PARAM, "alpha", 5.0).status == AckStatus.BAD_VALUE
        # Malformed datagrams: ignored (counted, logged), and the daemon still answers afterwards.
        receiver.send(b"\x00garbage", cport)
        bad = bytearray(encode(Control(request_id=9, camera_index=0xFFFF, command=1)))
        bad[8 + 6] = 99  # unknown command byte
        receiver.send(bytes(bad), cport)
        got = receiver.wait_for(lambda m: isinstance(m, ControlAck) and m.request_id == 9, 5.0)
        assert got and got[0].status == AckStatus.UNKNOWN_COMMAND
        # Stopped (idle): frames are consumed but not extracted.
        p.stdin.write(bg.tobytes())
        p.stdin.flush()
        time.sleep(0.2)
        assert not features(receiver.poll(0.1))
        assert ctl(receiver, cport, 4, Command.START).status == AckStatus.OK
        assert ctl(receiver, cport, 5, Command.SEND_FULL_IMAGE).status == AckStatus.OK
        assert ctl(receiver, cport, 6, Command.SEND_REGIONS, value=4).status == AckStatus.OK
        p.stdin.write(bg.tobytes() + one.tobytes())
        p.stdin.flush()
        fr = receiver.wait_for(lambda m: isinstance(m, FeatureFrame) and m.n_points == 1, 5.0)
        assert fr and abs(fr[0].points["x_dist"][0] - 60.4) < 0.06
        receiver.poll(0.3)
        chunks = [m for m in receiver.messages if isinstance(m, ImageChunk) and m.kind == 0]
        assert chunks and all(c.image_id == 5 for c in chunks)
        img = bytearray(chunks[0].total_bytes)
        for c in chunks:
            img[c.offset:c.offset + c.chunk_len] = c.data
        assert sum(c.chunk_len for c in chunks) == W * H
        assert bytes(img) == bg.tobytes()  # the next frame after the request
        regions = [m for m in receiver.messages if isinstance(m, ImageChunk) and m.kind == 1]
        assert regions and regions[0].width == 9 and regions[0].height == 9
        reg = np.frombuffer(regions[0].data, np.uint8).reshape(9, 9)
        assert (reg == one[66:75, 56:65]).all()
        # New background: the same frame then gives nothing.
        assert ctl(receiver, cport, 7, Command.TAKE_BACKGROUND).status == AckStatus.OK
        receiver.messages.clear()
        p.stdin.write(one.tobytes() + one.tobytes())
        p.stdin.flush()
        fr = receiver.wait_for(lambda m: isinstance(m, FeatureFrame) and m.camera_frame == 4, 5.0)
        assert fr and fr[0].n_points == 0
        assert ctl(receiver, cport, 8, Command.STOP).status == AckStatus.OK
    finally:
        p.stdin.close()
        rc = p.wait(10)
    err = p.stderr.read().decode()
    assert rc == 0, err
    assert "malformed CONTROL" in err


@pytest.mark.parametrize(
    "args, code, message",
    [
        (["--pixel-format", "rgb24", "--width", "8", "--height", "8"], 2, "unknown pixel format"),
        (["--width", "8", "--height", "8", "--bogus", "1"], 2, "unknown option"),
        (["--width", "8", "--height", "8", "--alpha", "nan"], 2, "finite"),
        (["--width", "8", "--height", "8", "--alpha", "7"], 2, "alpha"),
        (["--width", "8"], 3, "--width and --height"),
        (["--width", "8", "--height", "8", "--source", "raw", "--input", "/nonexistent/x.raw"], 3,
         "cannot open"),
        (["--source", "aravis", "--input", "No-Such-Camera-42"], 3, "cannot open camera"),
        (["--source", "v4l2", "--input", "/nonexistent/video9"], 3, "cannot open"),
        (["--width", "8", "--height", "8", "--max-points", "8161"], 2, "must be in 1..8160"),
        (["--width", "8", "--height", "8", "--control-allow", "10.0.0"], 2, "not an IPv4 address"),
        (["--width", "8", "--height", "8", "--control-allow", ","], 2, "needs an address"),
        (["--width", "7", "--height", "8", "--pixel-format", "yuyv"], 2, "even width"),
        (["--width", "8", "--height", "8", "--mask", "MASK"], 2, "must be exactly 8x8 = 64 bytes"),
    ],
)
def test_bad_configuration_exits_with_a_clear_error(edge_any: Path, receiver, tmp_path: Path, args, code,
                                                    message, no_sanitizer_report) -> None:
    mask = tmp_path / "mask.raw"
    mask.write_bytes(bytes(63))  # one byte short
    args = [str(mask) if a == "MASK" else a for a in args]
    p, _ = start(edge_any, receiver, *args, stdin=subprocess.DEVNULL)
    assert p.wait(30) == code
    err = p.stderr.read().decode()
    assert message in err
    no_sanitizer_report(err)


def test_wrong_frame_size_and_truncated_stream(edge_any: Path, receiver, tmp_path: Path,
                                               no_sanitizer_report) -> None:
    edge_bin = edge_any
    raw = tmp_path / "frames.raw"
    raw.write_bytes(bytes(W * H * 2 + 10))
    p, _ = start(edge_bin, receiver, "--width", str(W), "--height", str(H), "--input", str(raw),
                 stdin=subprocess.DEVNULL)
    assert p.wait(10) == 3
    assert "not a whole number" in p.stderr.read().decode()
    # Through a pipe the size is only known at the end: two frames then half a frame.
    p, _ = start(edge_bin, receiver, "--width", str(W), "--height", str(H))
    p.stdin.write(blob_frame([]).tobytes() * 2 + bytes(W * H // 2))
    p.stdin.close()
    assert p.wait(10) == 3
    err = p.stderr.read().decode()
    assert "ended inside frame 2" in err and f"got {W * H // 2} of {W * H} bytes" in err
    assert f"({W}x{H} mono8); check --width, --height, --pixel-format" in err
    no_sanitizer_report(err)
    receiver.poll(0.3)
    assert len(features(receiver.messages)) == 2  # the whole frames were not lost
    last = [m for m in receiver.messages if isinstance(m, EdgeStatus)][-1]
    assert last.state == 2 and "ended inside frame" in last.last_error


def test_config_file(edge_bin: Path, receiver, tmp_path: Path) -> None:
    cfg = tmp_path / "edge.toml"
    cfg.write_text(f'# an edge\n[source]\nsource = "raw"\nwidth = {W}\nheight = {H}\n'
                   '[detector]\ndiff_threshold = 250.0\n')
    p, _ = start(edge_bin, receiver, "--config", str(cfg))
    p.stdin.write(blob_frame([]).tobytes() + blob_frame([(50.5, 50.5)]).tobytes())
    p.stdin.close()
    assert p.wait(10) == 0, p.stderr.read().decode()
    receiver.poll(0.3)
    fr = features(receiver.messages)
    assert len(fr) == 2 and fr[1].n_points == 0  # threshold 250 from the file hides the blob
    bad = tmp_path / "bad.toml"
    bad.write_text("diff_threshold = \n")
    p, _ = start(edge_bin, receiver, "--config", str(bad), stdin=subprocess.DEVNULL)
    assert p.wait(10) == 2 and "bad.toml line 1" in p.stderr.read().decode()
