"""Unit tests of the UDP codec (SPEC §1) beyond the golden vectors."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from flytrack_host.protocol import (
    FEATURES_MAX_POINTS,
    OBJECT_DTYPE,
    POINT_DTYPE,
    CameraState,
    Command,
    Control,
    EdgeStatus,
    FeatureFlags,
    FeatureFrame,
    ImageChunk,
    LiveEstimates,
    PixelFormat,
    ProtocolError,
    assemble_image,
    canonical_fields,
    decode_datagram,
    encode,
    encode_features,
    encode_live_estimates,
    image_chunks,
    join_feature_parts,
    make_points,
)


def test_dtypes_match_spec() -> None:
    assert POINT_DTYPE.itemsize == 44 and OBJECT_DTYPE.itemsize == 52
    assert POINT_DTYPE.names == ("x_dist", "y_dist", "x_undist", "y_undist", "area", "peak_diff", "orientation",
                                 "eccentricity", "cur_val", "reserved", "mean_val", "sumsq_val")  # fmt: skip
    assert [POINT_DTYPE.fields[n][1] for n in POINT_DTYPE.names] == [0, 4, 8, 12, 16, 20, 24, 28, 32, 34, 36, 40]
    assert FEATURES_MAX_POINTS == 32


def _pts(n: int) -> np.ndarray:
    p = make_points(n)
    p["x_dist"] = np.arange(n) * 2.5
    p["peak_diff"] = (np.arange(n) * 7) % 23
    return p


def test_features_bytes_by_hand() -> None:
    p = _pts(2)
    msg = FeatureFrame(camera_index=3, seq=9, camera_frame=77, trigger_frame=-1, total_points=2, points=p)
    body = struct.pack("<HHIQqQQQHBBI", 3, 2, 9, 77, -1, 0, 0, 0, 2, 0, 1, 0)
    for r in p:
        body += struct.pack("<8fHHff", *[float(r[k]) for k in POINT_DTYPE.names[:8]], int(r["cur_val"]), 0,
                            float(r["mean_val"]), float(r["sumsq_val"]))  # fmt: skip
    assert encode(msg) == b"FT\x02\x01" + struct.pack("<HH", len(body), 0) + body


def test_decode_is_a_view_of_bytes_and_a_copy_of_bytearray() -> None:
    buf = bytearray(encode(FeatureFrame(camera_index=0, seq=1, camera_frame=2, total_points=3, points=_pts(3))))
    f = decode_datagram(buf)
    buf[8 + 56] ^= 0xFF  # the caller reuses its receive buffer
    assert f.points["x_dist"][0] == 0.0


def test_reserved_and_undefined_flags_are_ignored() -> None:
    w = bytearray(encode(FeatureFrame(camera_index=0, seq=1, camera_frame=2, total_points=1, points=_pts(1))))
    w[6:8] = struct.pack("<H", 0xFFF0)  # undefined flag bits
    w[60:64] = b"\x01\x02\x03\x04"  # fixed-part reserved
    w[64 + 34 : 64 + 36] = b"\xff\xff"  # point reserved
    f = decode_datagram(bytes(w))
    assert f.flags == 0 and "reserved" not in canonical_fields(f)
    again = encode(f)  # written as zero again
    assert again[6:8] == b"\0\0" and again[60:64] == bytes(4) and again[64 + 34 : 64 + 36] == b"\0\0"


def test_split_and_join() -> None:
    frame = FeatureFrame(camera_index=1, seq=0xFFFFFFFE, camera_frame=5, total_points=70, points=_pts(70))
    wires = encode_features(frame)
    assert [len(w) for w in wires] == [1472, 1472, 8 + 56 + 6 * 44]
    parts = [decode_datagram(w) for w in wires]
    assert [p.seq for p in parts] == [0xFFFFFFFE, 0xFFFFFFFF, 0]  # +1 per datagram, wrapping
    assert all(p.flags == FeatureFlags.SPLIT and p.part_count == 3 for p in parts)
    joined = join_feature_parts(parts[::-1])
    assert joined == frame
    with pytest.raises(ProtocolError):
        join_feature_parts(parts[:2])
    with pytest.raises(ProtocolError):
        join_feature_parts([parts[0], parts[0], parts[2]])


def test_truncate_keeps_strongest_in_order() -> None:
    p = _pts(50)
    (w,) = encode_features(FeatureFrame(camera_index=1, seq=0, camera_frame=5, total_points=50, points=p), True)
    f = decode_datagram(w)
    assert f.flags == FeatureFlags.TRUNCATED and f.n_points == 32 and f.total_points == 50
    kept = set(f.points["x_dist"].tolist())
    threshold = np.sort(p["peak_diff"])[-32]
    assert all(v in kept for v in p["x_dist"][p["peak_diff"] > threshold])
    assert np.all(np.diff(f.points["x_dist"]) > 0)  # original order


def test_encode_refuses_what_readers_reject() -> None:
    p = _pts(1)
    p["area"] = np.nan
    with pytest.raises(ProtocolError) as e:
        encode(FeatureFrame(camera_index=0, seq=0, camera_frame=0, total_points=1, points=p))
    assert e.value.name == "NOT_FINITE"
    with pytest.raises(ProtocolError) as e:
        encode(FeatureFrame(camera_index=0, seq=0, camera_frame=0, total_points=40, points=_pts(33)))
    assert e.value.name == "COUNT_OVERFLOW"
    with pytest.raises(ProtocolError) as e:
        encode(EdgeStatus(0, 1, 1, PixelFormat.MONO8, CameraState.IDLE, 0, camera_name="x" * 33))
    assert e.value.name == "BAD_FIELD"
    with pytest.raises(ProtocolError) as e:
        encode(Control(0, 70000, Command.START))
    assert e.value.name == "BAD_FIELD"
    with pytest.raises(ProtocolError) as e:
        encode(LiveEstimates(1, float("inf"), 0))
    assert e.value.name == "NOT_FINITE"
    with pytest.raises(ProtocolError) as e:
        encode(ImageChunk(0, 0, 1, 0, 0, 0, 0, 2, 2, 0, 4, b"12345"))
    assert e.value.name == "BAD_FIELD"
    with pytest.raises(ProtocolError) as e:  # more points than the frame claims to have found
        encode_features(FeatureFrame(camera_index=0, seq=0, camera_frame=0, total_points=1, points=_pts(2)))
    assert e.value.name == "COUNT_OVERFLOW"
    with pytest.raises(ProtocolError) as e:  # 256 datagrams would be needed
        encode_features(FeatureFrame(camera_index=0, seq=0, camera_frame=0, total_points=8161, points=_pts(8161)))
    assert e.value.name == "COUNT_OVERFLOW"


def test_error_messages_say_what_is_wrong() -> None:
    w = encode(EdgeStatus(0, 640, 480, PixelFormat.MONO8, CameraState.IDLE, 0))
    with pytest.raises(ProtocolError, match=r"TRUNCATED: .*143 payload bytes, the fixed part is 144"):
        decode_datagram(w[:-1])
    with pytest.raises(ProtocolError, match="state = 9 is not a CameraState"):
        decode_datagram(w[:15] + b"\x09" + w[16:])


def test_live_estimates_split() -> None:
    objs = np.zeros(60, OBJECT_DTYPE)
    objs["obj_id"] = np.arange(60)
    est = LiveEstimates(10, 1234.5, 7, 2.0, objects=objs)
    wires = encode_live_estimates(est)
    parts = [decode_datagram(w) for w in wires]
    assert [p.n_objects for p in parts] == [27, 27, 6]
    assert [(p.part_index, p.part_count, p.flags, p.seq) for p in parts] == [(i, 3, 1, 7 + i) for i in range(3)]
    assert np.concatenate([p.objects for p in parts])["obj_id"].tolist() == list(range(60))
    (one,) = encode_live_estimates(LiveEstimates(10, 1234.5, 7, 2.0, objects=objs[:3]))
    assert decode_datagram(one).flags == 0


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_image_chunks_roundtrip(dtype) -> None:
    img = (np.arange(50 * 61) * 37 % 4099).astype(dtype).reshape(50, 61)
    chunks = [decode_datagram(encode(c)) for c in image_chunks(2, 0, 99, 5, 0, 0, img)]
    assert all(c.chunk_len <= 1428 for c in chunks)
    assert np.array_equal(assemble_image(chunks[::-1]), img)
    with pytest.raises(ProtocolError):
        assemble_image(chunks[1:])
