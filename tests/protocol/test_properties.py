"""Hypothesis round trips of every message type, and fuzzing: on any bytes only ProtocolError comes out."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flytrack_host.protocol import (
    CLUSTER_DTYPE,
    OBJECT_DTYPE,
    POINT_DTYPE,
    SERIAL_MESSAGE_TYPES,
    UDP_MESSAGE_TYPES,
    WINGEDGE_DTYPE,
    AckStatus,
    CameraState,
    Command,
    Control,
    ControlAck,
    DvsClusters,
    DvsDecoder,
    DvsEncoder,
    DvsWingbeat,
    EdgeStatus,
    FeatureFrame,
    FrameSplitter,
    ImageChunk,
    ImageKind,
    Info,
    LiveEstimates,
    PixelFormat,
    ProtocolError,
    Pulse,
    Rate,
    SetName,
    SetOutput,
    SetRate,
    canonical_fields,
    decode_datagram,
    decode_message,
    encode,
    encode_features,
    encode_message,
    join_feature_parts,
)
from flytrack_host.protocol import trigger_link as tl
from flytrack_host.protocol.vectors import load_vectors

SETTINGS = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])

u8, u16 = st.integers(0, 0xFF), st.integers(0, 0xFFFF)
u32, u64 = st.integers(0, 0xFFFFFFFF), st.integers(0, 2**64 - 1)
f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
f64 = st.floats(allow_nan=False, allow_infinity=False)
# Text that fits its field once UTF-8 encoded, without NUL.
def text(size: int) -> st.SearchStrategy[str]:
    return st.text(st.characters(blacklist_characters="\0", blacklist_categories=("Cs",)), max_size=size).filter(
        lambda s: len(s.encode()) <= size
    )


def records(dtype: np.dtype, max_n: int, nan_ok: tuple[str, ...] = ()) -> st.SearchStrategy[np.ndarray]:
    """Random record arrays: random bytes, then every f32 field forced finite (NaN kept where allowed)."""

    def build(raw: bytes) -> np.ndarray:
        arr = np.frombuffer(raw, dtype).copy()
        for name in dtype.names:
            if name.startswith("reserved"):
                arr[name] = 0
            elif dtype.fields[name][0].base.kind == "f":
                v = arr[name]
                bad = ~np.isfinite(v) if name not in nan_ok else np.isinf(v)
                v[bad] = 1.5
        return arr

    return st.integers(0, max_n).flatmap(
        lambda n: st.binary(min_size=n * dtype.itemsize, max_size=n * dtype.itemsize).map(build)
    )


features = st.builds(
    lambda ci, seq, cf, tf, dts, rcv, done, pts, extra, flags, split: FeatureFrame(
        camera_index=ci, seq=seq, camera_frame=cf, trigger_frame=tf, device_timestamp_ns=dts, edge_recv_ns=rcv,
        edge_done_ns=done, total_points=min(len(pts) + extra, 0xFFFF), flags=flags, points=pts,
        part_index=split[0], part_count=split[1],
    ),
    u16, u32, u64, st.integers(-(2**63), 2**63 - 1), u64, u64, u64,
    records(POINT_DTYPE, 32, ("orientation", "eccentricity")), st.integers(0, 100), st.integers(0, 3),
    st.integers(1, 255).flatmap(lambda c: st.tuples(st.integers(0, c - 1), st.just(c))),
)  # fmt: skip
status = st.builds(EdgeStatus, u16, u16, u16, st.sampled_from(PixelFormat), st.sampled_from(CameraState), u32,
                   u32, u64, u64, f32, f32, f32, text(32), text(64))  # fmt: skip
control = st.builds(Control, u32, u16, st.sampled_from(Command), text(24), f64)
control_ack = st.builds(ControlAck, u32, u16, u8, st.sampled_from(AckStatus), text(48))


@st.composite
def image(draw) -> ImageChunk:
    bpp = draw(st.sampled_from([1, 2]))
    w, h = draw(st.integers(0, 2000)), draw(st.integers(0, 2000))
    total = w * h * bpp
    n = draw(st.integers(0, min(1428, total)))
    off = draw(st.integers(0, total - n))
    return ImageChunk(draw(u16), draw(st.sampled_from(ImageKind)), bpp, draw(u32), draw(u64), draw(u16),
                      draw(u16), w, h, off, total, draw(st.binary(min_size=n, max_size=n)))  # fmt: skip


def _covariances(c: np.ndarray) -> np.ndarray:
    """Random cluster records made valid (SPEC 1.6): variances >= 0, |cov_xy| <= sqrt(var_x var_y)."""
    c["var_x"], c["var_y"] = np.abs(c["var_x"]), np.abs(c["var_y"])
    lim = np.sqrt(c["var_x"].astype(np.float64) * c["var_y"]) * 0.999
    c["cov_xy"] = np.clip(c["cov_xy"].astype(np.float64), -lim, lim).astype(np.float32)
    return c


clusters = st.builds(
    lambda ci, seq, t0, t1, done, tf, period, syncs, synced, recs: DvsClusters(
        ci, seq, t0, t1, done, tf, abs(period) if not synced else max(abs(period), 1.0), syncs, int(synced),
        _covariances(recs)),
    u16, u32, u64, u64, u64, f64, f32, u32, st.booleans(), records(CLUSTER_DTYPE, 35),
)  # fmt: skip
wingbeat = st.builds(DvsWingbeat, u16, u32, u64, u64, records(WINGEDGE_DTYPE, 8))
live = st.builds(
    lambda tf, tt, seq, lat, split, flags, objs: LiveEstimates(tf, tt, seq, lat, split[0], split[1], flags, objs),
    u64, f64, u32, f32, st.integers(1, 255).flatmap(lambda c: st.tuples(st.integers(0, c - 1), st.just(c))),
    st.integers(0, 1), records(OBJECT_DTYPE, 27),
)  # fmt: skip
ANY_UDP = st.one_of(features, status, control, control_ack, image(), clusters, wingbeat, live)


def test_every_udp_type_is_generated() -> None:
    assert len(UDP_MESSAGE_TYPES) == 8  # the strategies above cover these eight


@SETTINGS
@given(ANY_UDP)
def test_udp_roundtrip(msg) -> None:
    wire = encode(msg)
    assert len(wire) <= 1472
    got = decode_datagram(wire)
    assert got == msg
    assert encode(got) == wire
    assert canonical_fields(got) == canonical_fields(msg)


@SETTINGS
@given(features, st.integers(0, 200), st.booleans())
def test_split_features_roundtrip(frame: FeatureFrame, extra_points: int, truncate: bool) -> None:
    pts = np.concatenate([frame.points] * (1 + extra_points // max(1, frame.n_points)))[: frame.n_points + extra_points]
    frame = FeatureFrame(camera_index=frame.camera_index, seq=frame.seq, camera_frame=frame.camera_frame,
                         total_points=len(pts) + (frame.total_points - frame.n_points), points=pts)  # fmt: skip
    wires = encode_features(frame, truncate=truncate)
    parts = [decode_datagram(w) for w in wires]
    if truncate or len(pts) <= 32:
        assert len(parts) == 1 and parts[0].n_points == min(32, len(pts))
        assert parts[0].truncated == (frame.total_points > parts[0].n_points)
    else:
        assert len(parts) == -(-len(pts) // 32) and all(p.split for p in parts)
        joined = join_feature_parts(parts)
        assert joined.points.tobytes() == frame.points.tobytes()
        assert joined.truncated == (frame.total_points > len(pts))


serial_msgs = st.one_of(
    [st.builds(c) for c in SERIAL_MESSAGE_TYPES if not tl.fields(c)]
    + [
        st.builds(SetRate, st.integers(1, 5), u16),
        st.builds(Pulse, u8, u32, u16),
        st.builds(SetOutput, u8, st.integers(0, 1)),
        st.builds(SetName, text(16)),
        st.builds(Info, u8, u8, u8, u8, st.integers(1, 2), u8, u32, text(16)),
        st.builds(tl.Ack, u8),
        st.builds(Rate, u32, st.integers(1, 5), u16),
        st.builds(tl.Clock, u32, u16, u16, u8),
        st.builds(tl.Event, u8, st.integers(0, 1), u32, u16),
        st.builds(tl.Error, u8, u8),
    ]
)


@SETTINGS
@given(serial_msgs, u8)
def test_serial_roundtrip(msg, seq: int) -> None:
    wire = encode_message(msg, seq)
    assert wire[-1] == 0 and 0 not in wire[:-1] and len(wire) - 1 <= tl.MAX_WIRE_FRAME
    assert decode_message(wire[:-1]) == (seq, msg)


@SETTINGS
@given(st.lists(st.tuples(serial_msgs, u8), min_size=1, max_size=8), st.binary(max_size=20), st.data())
def test_splitter_any_chunking(msgs, garbage: bytes, data) -> None:
    stream = garbage + b"\0" + b"".join(encode_message(m, s) for m, s in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    sp = FrameSplitter()
    frames: list[bytes] = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        frames += sp.feed(stream[a:b])
    decoded = []
    for f in frames:
        try:
            decoded.append(decode_message(f))
        except ProtocolError:
            pass  # the garbage frame
    assert decoded[-len(msgs) :] == [(s, m) for m, s in msgs]


@SETTINGS
@given(st.lists(st.tuples(st.integers(0, 127), st.integers(0, 127), st.integers(0, 1), st.integers(0, 200_000)),
                max_size=300), st.integers(0, 300))  # fmt: skip
def test_dvs_roundtrip_across_packets(events, cut: int) -> None:
    ev = np.array(sorted(events, key=lambda e: e[3]), dtype=np.int64).reshape(-1, 4)
    enc, dec = DvsEncoder(), DvsDecoder()
    got = np.concatenate([dec.decode(enc.encode(*part.T)) for part in (ev[:cut], ev[cut:])])
    assert np.array_equal(np.stack([got["x"], got["y"], got["p"], got["t"]], 1).astype(np.int64), ev)
    assert dec.offset == enc.offset


# ---------------------------------------------------------------- fuzzing

VALID_WIRES = [v.data for v in load_vectors(Path(__file__).resolve().parents[2] / "protocol" / "vectors") if v.valid]


def _only_protocol_errors(fn, data: bytes) -> None:
    try:
        fn(data)
    except ProtocolError as exc:
        assert exc.name
    # anything else propagates and fails the test


@settings(max_examples=250, deadline=None)
@given(st.binary(max_size=1600))
def test_fuzz_decode_datagram_random(data: bytes) -> None:
    _only_protocol_errors(decode_datagram, data)
    _only_protocol_errors(decode_datagram, b"FT\x02" + data[:1] + len(data[1:]).to_bytes(2, "little") + data[1:])


@settings(max_examples=250, deadline=None)
@given(st.sampled_from(VALID_WIRES), st.lists(st.tuples(st.integers(0, 2000), u8), max_size=6),
       st.integers(0, 2000))  # fmt: skip
def test_fuzz_mutated_vectors(wire: bytes, edits, cut: int) -> None:
    b = bytearray(wire)
    for pos, val in edits:
        if b:
            b[pos % len(b)] = val
    b = bytes(b[: max(cut, len(b) // 2)])
    _only_protocol_errors(decode_datagram, b)
    _only_protocol_errors(lambda d: decode_message(d[:-1] if d.endswith(b"\0") else d), b)
    _only_protocol_errors(DvsDecoder().decode, b)


@settings(max_examples=250, deadline=None)
@given(st.binary(max_size=80))
def test_fuzz_decode_frame(data: bytes) -> None:
    _only_protocol_errors(tl.decode_frame, data)
    _only_protocol_errors(decode_message, tl.cobs_encode(data))
    sp = FrameSplitter()
    for f in sp.feed(data):
        _only_protocol_errors(decode_message, f)


@settings(max_examples=250, deadline=None)
@given(st.binary(max_size=400))
def test_fuzz_dvs_decoder(data: bytes) -> None:
    dec = DvsDecoder(0x4000)
    before = dec.offset
    try:
        ev = dec.decode(data)
    except ProtocolError:
        assert dec.offset == before  # a rejected packet changes nothing
    else:
        assert len(ev) <= len(data) // 4
