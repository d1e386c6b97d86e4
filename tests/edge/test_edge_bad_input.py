"""flytrack-edge against bad input, run on the plain daemon and on its ASan + UBSan build
(flytrack-edge-san, which aborts on the first finding, leaks included): random, truncated and
oversized CONTROL datagrams, broken Y4M headers and FRAME lines, streams ending inside a frame,
images and regions at the frame's borders, the max_points cap, and the CONTROL sender allow-list.

Each daemon's stderr goes to a file (thousands of log lines could fill a pipe and block it)."""

from __future__ import annotations

import random
import socket
import struct
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
    decode_datagram,
    encode,
)


class Edge:
    """One daemon process with its stderr in a file."""

    def __init__(self, binary: Path, receiver, tmp_path: Path, *args: str, stdin=subprocess.PIPE) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        self.cport = s.getsockname()[1]
        s.close()
        self.log = tmp_path / f"edge-{self.cport}.log"
        self._err = open(self.log, "wb")  # noqa: SIM115 - closed in wait()
        cmd = [str(binary), "--host", "127.0.0.1", "--port", str(receiver.port), "--control-port",
               str(self.cport), "--bind", "127.0.0.1", "--status-interval-ms", "50", *args]
        self.p = subprocess.Popen(cmd, stdin=stdin, stdout=subprocess.DEVNULL, stderr=self._err)
        self.receiver = receiver

    def write(self, data: bytes) -> None:
        self.p.stdin.write(data)
        self.p.stdin.flush()

    def wait(self, timeout: float = 20.0) -> tuple[int, str]:
        if self.p.stdin:
            self.p.stdin.close()
        try:
            rc = self.p.wait(timeout)
        finally:
            if self.p.poll() is None:
                self.p.kill()
                self.p.wait()
            self._err.close()
        err = self.log.read_text(errors="replace")
        print(f"--- {self.p.args[0]} exited {self.p.returncode}; stderr tail:\n{err[-4000:]}")  # shown on failure
        return rc, err

    def up(self) -> None:
        assert self.receiver.wait_for(lambda m: isinstance(m, EdgeStatus), 10.0), "no STATUS: daemon not up"

    def ctl(self, rid: int, cmd: int, param: str = "", value: float = 0.0, timeout: float = 5.0) -> ControlAck:
        self.receiver.send(encode(Control(request_id=rid, camera_index=0xFFFF, command=int(cmd), param=param,
                                          value=value)), self.cport)
        acks = self.receiver.wait_for(lambda m: isinstance(m, ControlAck) and m.request_id == rid, timeout)
        assert acks, f"no CONTROL_ACK for request {rid}"
        return acks[0]


def spots(w: int, h: int, where: list[tuple[int, int]], bg: int = 20, val: int = 220) -> np.ndarray:
    img = np.full((h, w), bg, np.uint8)
    for x, y in where:
        img[y, x] = val
    return img


def as_format(img: np.ndarray, fmt: str) -> bytes:
    if fmt == "mono16":
        return img.astype("<u2").tobytes()
    if fmt == "yuyv":
        out = np.full((img.shape[0], img.shape[1] * 2), 128, np.uint8)
        out[:, 0::2] = img
        return out.tobytes()
    return img.tobytes()


def assemble(chunks: list[ImageChunk]) -> dict[tuple[int, int], tuple[ImageChunk, bytes]]:
    """(kind, image_id) -> (first chunk, the whole image's bytes); every image must be complete.
    (Full frames carry the request's id, regions a running counter: the kind tells them apart.)"""
    by_id: dict[tuple[int, int], list[ImageChunk]] = {}
    for c in chunks:
        by_id.setdefault((int(c.kind), c.image_id), []).append(c)
    out = {}
    for iid, cs in by_id.items():
        buf = bytearray(cs[0].total_bytes)
        for c in cs:
            buf[c.offset:c.offset + c.chunk_len] = bytes(c.data)
        assert sum(c.chunk_len for c in cs) == cs[0].total_bytes, f"image {iid} incomplete"
        out[iid] = (cs[0], bytes(buf))
    return out


# ---- CONTROL: random, truncated, oversized ----------------------------------------------------------

PARAMS = ["alpha", "n_sigma", "diff_threshold", "bg_update_interval", "polarity", "clear_fraction",
          "despeckle_threshold", "min_area", "subtract_cut", "max_points", "max_candidates", "", "x" * 23,
          "width"]
VALUES = [0.0, 1.0, -1.0, 0.5, 2.0, 7.0, 30.0, 255.0, 256.0, 8160.0, 8161.0, 1e5, 2.0**32, -2.0**31, 1e308,
          5e-324, 1e-9, 0.999999, 65535.0, 65536.0]


def fuzz_datagram(rng: random.Random) -> bytes:
    base = encode(Control(request_id=rng.randrange(1, 10_000_000), camera_index=rng.choice([0xFFFF, 0, 7]),
                          command=rng.choice([1, 2, 3, 4, 5, 6]), param=rng.choice(PARAMS),
                          value=rng.choice(VALUES)))
    kind = rng.randrange(7)
    if kind == 0:  # as is: valid framing, odd values
        return base
    if kind == 1:  # truncated
        return base[:rng.randrange(len(base))]
    if kind == 2:  # oversized: a valid message with a tail, up to past the daemon's 2048-byte buffer
        return base + rng.randbytes(rng.randrange(1, 3000))
    if kind == 3:  # random bytes
        return rng.randbytes(rng.randrange(0, 120))
    b = bytearray(base)
    if kind == 4:  # bit flips
        for _ in range(rng.randrange(1, 6)):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
    elif kind == 5:  # NaN / infinity / denormal value, or an unknown command byte
        if rng.random() < 0.5:
            b[-8:] = struct.pack("<d", rng.choice([float("nan"), float("inf"), -float("inf"), 5e-324]))
        else:
            b[8 + 6] = rng.choice([0, 7, 99, 255])
    else:  # param text without terminator / with bytes after the NUL
        b[8 + 8:8 + 32] = rng.randbytes(24)
    return bytes(b)


def test_control_fuzz(edge_any: Path, receiver, tmp_path: Path, no_sanitizer_report) -> None:
    w, h = 64, 48
    e = Edge(edge_any, receiver, tmp_path, "--width", str(w), "--height", str(h))
    rng = random.Random(4)
    frames = [spots(w, h, []), spots(w, h, [(0, 0), (63, 47), (0, 47), (63, 0), (31, 0), (20, 30)])]
    written = 0
    try:
        e.up()
        for batch in range(48):  # 48 x 64 = 3072 datagrams
            for _ in range(64):
                receiver.send(fuzz_datagram(rng), e.cport)
            e.write(frames[batch % 2].tobytes())
            written += 1
            # Sync: the daemon answers an unknown parameter, so it has served the batch and is alive.
            a = e.ctl(20_000_000 + batch, Command.SET_PARAM, "sync_probe", 1.0)
            assert a.status == AckStatus.UNKNOWN_PARAM
        # Still fully working: sane parameters back, START, a blob found.
        for k, (name, v) in enumerate([("alpha", 0.01), ("n_sigma", 7), ("diff_threshold", 30), ("min_area", 1),
                                       ("polarity", 0), ("clear_fraction", 0.3), ("despeckle_threshold", 5),
                                       ("max_points", 100)]):
            assert e.ctl(30_000_000 + k, Command.SET_PARAM, name, v).status == AckStatus.OK
        assert e.ctl(30_000_100, Command.START).status == AckStatus.OK
        assert e.ctl(30_000_101, Command.TAKE_BACKGROUND).status == AckStatus.OK
        e.write(frames[0].tobytes() + spots(w, h, [(30, 20)]).tobytes())
        written += 2
        got = receiver.wait_for(lambda m: isinstance(m, FeatureFrame) and m.camera_frame == written - 1, 5.0)
        assert got and got[0].n_points == 1
        assert abs(got[0].points["x_dist"][0] - 30) < 1e-3 and abs(got[0].points["y_dist"][0] - 20) < 1e-3
    finally:
        rc, err = e.wait()
    no_sanitizer_report(err)
    assert rc == 0, err[-3000:]
    receiver.poll(0.3)
    last = [m for m in receiver.messages if isinstance(m, EdgeStatus)][-1]
    assert last.frames_seen == written and last.state == 3  # the final STATUS: stopped
    # The fuzz reached every answer and the image paths (so it exercised more than the decoder).
    statuses = {int(m.status) for m in receiver.messages if isinstance(m, ControlAck)}
    assert statuses == {int(s) for s in AckStatus}, statuses
    kinds = {int(m.kind) for m in receiver.messages if isinstance(m, ImageChunk)}
    assert kinds == {0, 1}, kinds
    # Malformed ones are logged, but not each of thousands.
    n_logged = err.count("malformed CONTROL")
    assert 1 <= n_logged <= 15, n_logged


def test_control_max_points_capped(edge_any: Path, receiver, tmp_path: Path, no_sanitizer_report) -> None:
    # 9216 isolated pixels: more regions than 255 parts x 32 points can carry.
    w = h = 192
    grid = [(x, y) for y in range(0, h, 2) for x in range(0, w, 2)]
    e = Edge(edge_any, receiver, tmp_path, "--width", str(w), "--height", str(h))
    try:
        e.up()
        for rid, v in ((1, 100000), (2, 8161), (3, 2.0**32 - 1)):
            a = e.ctl(rid, Command.SET_PARAM, "max_points", v)
            assert a.status == AckStatus.BAD_VALUE, a
        assert e.ctl(4, Command.SET_PARAM, "max_points", 8160).status == AckStatus.OK
        e.write(spots(w, h, []).tobytes() + spots(w, h, grid).tobytes())
        end = time.monotonic() + 10
        while time.monotonic() < end:
            receiver.poll(0.05)
            if len([m for m in receiver.messages if isinstance(m, FeatureFrame) and m.camera_frame == 1]) >= 255:
                break
        # The daemon goes on: the next frame is processed too.
        e.write(spots(w, h, [(5, 5)]).tobytes())
        assert receiver.wait_for(lambda m: isinstance(m, FeatureFrame) and m.camera_frame == 2, 5.0)
    finally:
        rc, err = e.wait()
    no_sanitizer_report(err)
    assert rc == 0, err[-3000:]
    parts = [m for m in receiver.messages if isinstance(m, FeatureFrame) and m.camera_frame == 1]
    assert len(parts) == 255
    assert {m.part_count for m in parts} == {255}
    assert sorted(m.part_index for m in parts) == list(range(255))
    assert all(m.split and m.truncated for m in parts)
    assert {m.total_points for m in parts} == {len(grid)}
    assert sum(m.n_points for m in parts) == 8160


# ---- Y4M headers and FRAME lines -----------------------------------------------------------------------

MONO = b"YUV4MPEG2 W16 H8 F30:1 Cmono\n"
FR = bytes(128)  # one 16x8 mono frame


@pytest.mark.parametrize(
    "data, message",
    [
        (b"", "ended before its header"),
        (b"YUV4MPEG2 W16 H8", "ended before its header"),
        (b"YUV4MPEG2 " + b"X" * 600 + b"\n", "header longer than 511 bytes"),
        (b"YUV4MPEG2 W0 H8\n", "bad size W0 H8"),
        (b"YUV4MPEG2 H8\n", "bad size W0 H8"),
        (b"YUV4MPEG2 W99999 H8\n", "bad size W99999"),
        (b"YUV4MPEG2 W99999999999999999999999999 H8\n", "bad size"),
        (b"YUV4MPEG2 W-16 H8\n", "bad size"),
        (b"YUV4MPEG2 Wabc H8\n", 'bad size field "Wabc"'),
        (b"YUV4MPEG2 W16x H8\n", 'bad size field "W16x"'),
        (b"NOTY4M W16 H8\n", "not Y4M"),
        (b"YUV4MPEG2 W16 H8 C420p10\n", "C420p10 is not supported"),
        (b"YUV4MPEG2 W16 H8 C" + b"4" * 100 + b"\n", "is not supported"),
        (MONO + b"FRAME" + b"x" * 300 + b"\n" + FR, "frame header longer than 255 bytes"),
        (MONO + b"FRA", "ended inside a FRAME header"),
        (MONO + b"FRAME\n" + FR + b"FRAMX\n" + FR, 'expected FRAME, got "FRAMX" (frame 1'),
        (MONO + b"FRAMEjunk\n" + FR, "expected FRAME"),
        (MONO + b"\n" + FR, "expected FRAME"),
        (MONO + b"FRAME\n" + FR + b"FRAME\n" + FR[:100], "ended inside frame 1: got 100 of 128 bytes"),
        (MONO + b"FRAME\n", "ended inside frame 0: got 0 of 128 bytes"),
        # Frames written without their chroma although the header says 4:2:0: misaligned, caught.
        (b"YUV4MPEG2 W16 H8 C420jpeg\n" + (b"FRAME\n" + FR) * 4, "expected FRAME"),
    ],
)
def test_bad_y4m_is_a_clear_error(edge_any: Path, receiver, tmp_path: Path, data: bytes, message: str,
                                  no_sanitizer_report) -> None:
    src = tmp_path / "in.y4m"
    src.write_bytes(data)
    e = Edge(edge_any, receiver, tmp_path, "--source", "y4m", "--input", str(src), stdin=subprocess.DEVNULL)
    rc, err = e.wait()
    no_sanitizer_report(err)
    assert rc == 3, err
    assert message in err, err


def test_y4m_pipe_ending_inside_a_frame(edge_any: Path, receiver, tmp_path: Path, no_sanitizer_report) -> None:
    e = Edge(edge_any, receiver, tmp_path, "--source", "y4m", "--input", "-")
    e.write(MONO + (b"FRAME\n" + FR) * 3 + b"FRAME\n" + FR[:77])
    rc, err = e.wait()
    no_sanitizer_report(err)
    assert rc == 3 and "ended inside frame 3: got 77 of 128 bytes (a 16x8 Y4M frame" in err, err
    receiver.poll(0.3)
    assert len([m for m in receiver.messages if isinstance(m, FeatureFrame)]) == 3  # whole frames kept


@pytest.mark.parametrize("fmt, bpp", [("mono16", 2), ("yuyv", 2)])
def test_raw_pipe_partial_frame_names_the_frame_size(edge_any: Path, receiver, tmp_path: Path, fmt: str,
                                                     bpp: int, no_sanitizer_report) -> None:
    w, h = 20, 10
    e = Edge(edge_any, receiver, tmp_path, "--width", str(w), "--height", str(h), "--pixel-format", fmt)
    e.write(bytes(w * h * bpp) + bytes(33))  # e.g. the sender's frames are 1 px wider than configured
    rc, err = e.wait()
    no_sanitizer_report(err)
    assert rc == 3, err
    assert f"ended inside frame 1: got 33 of {w * h * bpp} bytes ({w}x{h} {fmt}); check --width" in err


# ---- images and regions at the borders ------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["mono8", "mono16", "yuyv"])
def test_full_image_and_regions_at_borders(edge_any: Path, receiver, tmp_path: Path, fmt: str,
                                           no_sanitizer_report) -> None:
    w, h = 62, 47  # odd height; even width (YUYV)
    where = [(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1), (30, 0), (0, 20), (w - 1, 25), (30, h - 1),
             (2, 2), (w - 3, h - 3)]
    bg, img = spots(w, h, []), spots(w, h, where)
    bpp = 2 if fmt == "mono16" else 1
    e = Edge(edge_any, receiver, tmp_path, "--width", str(w), "--height", str(h), "--pixel-format", fmt)
    results = {}
    try:
        e.up()
        e.write(as_format(bg, fmt))
        for k, half in enumerate((3, 1, 255)):
            receiver.messages.clear()
            assert e.ctl(10 + k, Command.SEND_REGIONS, value=half).status == AckStatus.OK
            assert e.ctl(20 + k, Command.SEND_FULL_IMAGE).status == AckStatus.OK
            e.write(as_format(img, fmt))
            fr = receiver.wait_for(lambda m, k=k: isinstance(m, FeatureFrame) and m.camera_frame == k + 1, 5.0)
            assert fr and fr[0].n_points == len(where)
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:
                receiver.poll(0.05)
                imgs = assemble([m for m in receiver.messages if isinstance(m, ImageChunk)]) \
                    if _complete(receiver.messages) else None
                if imgs and len(imgs) == len(where) + 1:
                    break
            results[half] = assemble([m for m in receiver.messages if isinstance(m, ImageChunk)])
    finally:
        rc, err = e.wait()
    no_sanitizer_report(err)
    assert rc == 0, err[-3000:]
    for k, half in enumerate((3, 1, 255)):
        imgs = results[half]
        full = [v for v in imgs.values() if v[0].kind == 0]
        assert len(full) == 1 and full[0][0].image_id == 20 + k
        c, data = full[0]
        assert (c.width, c.height, c.bytes_per_pixel) == (w, h, bpp)
        want_full = img.astype("<u2").tobytes() if bpp == 2 else img.tobytes()
        assert data == want_full
        regions = [v for v in imgs.values() if v[0].kind == 1]
        boxes = set()
        for c, data in regions:
            boxes.add((c.x0, c.y0, c.width, c.height))
            cut = img[c.y0:c.y0 + c.height, c.x0:c.x0 + c.width]
            assert data == (cut.astype("<u2").tobytes() if bpp == 2 else cut.tobytes())
        want = set()
        for x, y in where:
            x0, y0 = max(0, x - half), max(0, y - half)
            x1, y1 = min(w - 1, x + half), min(h - 1, y + half)
            want.add((x0, y0, x1 - x0 + 1, y1 - y0 + 1))
        assert boxes == want and len(regions) == len(where)


def _complete(msgs: list) -> bool:
    chunks = [m for m in msgs if isinstance(m, ImageChunk)]
    by_id: dict[tuple[int, int], int] = {}
    for c in chunks:
        key = (int(c.kind), c.image_id)
        by_id[key] = by_id.get(key, 0) + c.chunk_len
    return bool(chunks) and all(by_id[(int(c.kind), c.image_id)] == c.total_bytes for c in chunks)


# ---- CONTROL sender allow-list ----------------------------------------------------------------------------

def test_control_allow_list(edge_any: Path, receiver, tmp_path: Path, no_sanitizer_report) -> None:
    cfg = tmp_path / "edge.toml"
    cfg.write_text('[network]\ncontrol_allow = ["127.0.0.2", "10.1.2.3"]\n')
    # The file's list and the flag's add up (the option is repeatable).
    e = Edge(edge_any, receiver, tmp_path, "--width", "16", "--height", "8", "--config", str(cfg),
             "--control-allow", "10.9.9.9")
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.2", 0))
    other.settimeout(5.0)
    try:
        e.up()
        # From 127.0.0.1 (not listed): dropped, no answer; STATUS says so.
        for rid in (1, 2, 3):
            receiver.send(encode(Control(request_id=rid, camera_index=0xFFFF, command=int(Command.STOP))), e.cport)
        st = receiver.wait_for(lambda m: isinstance(m, EdgeStatus) and "not in --control-allow" in m.last_error,
                               5.0)
        assert st and "127.0.0.1" in st[0].last_error
        assert not [m for m in receiver.messages if isinstance(m, ControlAck)]
        # From 127.0.0.2 (listed): answered, to that sender.
        other.sendto(encode(Control(request_id=4, camera_index=0xFFFF, command=int(Command.SET_PARAM),
                                    param="diff_threshold", value=40.0)), ("127.0.0.1", e.cport))
        data, _ = other.recvfrom(2048)
        ack = decode_datagram(data)
        assert isinstance(ack, ControlAck) and ack.request_id == 4 and ack.status == AckStatus.OK
        # The dropped STOP had no effect: frames are still extracted.
        e.write(bytes(128) * 2)
        assert receiver.wait_for(lambda m: isinstance(m, FeatureFrame) and m.camera_frame == 1, 5.0)
    finally:
        other.close()
        rc, err = e.wait()
    no_sanitizer_report(err)
    assert rc == 0, err
    assert err.count("not in --control-allow (further ones are only counted)") == 1
    assert "dropped 3 CONTROL datagrams from senders not in --control-allow" in err


def _local_non_loopback() -> str | None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.connect(("192.0.2.1", 9))  # no packet is sent: only picks the outgoing interface
        addr = s.getsockname()[0]
    except OSError:
        return None
    finally:
        s.close()
    return None if addr.startswith("127.") else addr


def test_control_allow_default_is_host_and_loopback(edge_bin: Path, receiver, tmp_path: Path) -> None:
    addr = _local_non_loopback()
    if addr is None:
        pytest.skip("no non-loopback IPv4 address on this machine")
    e = Edge(edge_bin, receiver, tmp_path, "--width", "16", "--height", "8", "--bind", "0.0.0.0")
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind((addr, 0))
    try:
        e.up()
        other.sendto(encode(Control(request_id=1, camera_index=0xFFFF, command=int(Command.START))),
                     (addr, e.cport))
        st = receiver.wait_for(lambda m: isinstance(m, EdgeStatus) and "not in --control-allow" in m.last_error,
                               5.0)
        assert st and addr in st[0].last_error
        assert e.ctl(2, Command.START).status == AckStatus.OK  # loopback (and --host) still accepted
    finally:
        other.close()
        rc, err = e.wait()
    assert rc == 0, err
