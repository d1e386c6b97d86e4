"""Every valid UDP golden vector, rebuilt by a second encoder written from SPEC.md §1 alone.

protocol/vectors/generate.py makes the valid vectors with the Python codec they then test. This test
does not use that codec: it reads each vector's canonical fields (SPEC §5), packs them with `struct`
from the SPEC's tables below (offsets, types, reserved fields as 0), and requires the vector's bytes.
A codec bug that moved a field, swapped two, or wrote a reserved field would be caught here even though
the generator and the Python runner agreed with it. (NaN payload bits do not survive the canonical
text, "nan": there the two are compared field by field, NaN equal to NaN.) The serial trigger link and
the DVS USB words are not covered here (their `indep_*` vectors are).
"""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path

import pytest

VEC = Path(__file__).resolve().parents[2] / "protocol" / "vectors"

# (field, struct code); None = reserved (written 0, not printed). From SPEC.md §1.1-1.8, protocol version 2.
FIXED = {
    1: [("camera_index", "H"), ("n_points", "H"), ("seq", "I"), ("camera_frame", "Q"), ("trigger_frame", "q"),
        ("device_timestamp_ns", "Q"), ("edge_recv_ns", "Q"), ("edge_done_ns", "Q"), ("total_points", "H"),
        ("part_index", "B"), ("part_count", "B"), (None, "I")],
    2: [("camera_index", "H"), ("width", "H"), ("height", "H"), ("pixel_format", "B"), ("state", "B"),
        ("seq", "I"), ("last_error_code", "I"), ("frames_seen", "Q"), ("frames_dropped", "Q"), ("fps", "f"),
        ("proc_us_mean", "f"), ("proc_us_max", "f"), (None, "I"), ("camera_name", "32s"), ("last_error", "64s")],
    3: [("request_id", "I"), ("camera_index", "H"), ("command", "B"), (None, "B"), ("param", "24s"),
        ("value", "d")],
    4: [("request_id", "I"), ("camera_index", "H"), ("command", "B"), ("status", "B"), ("message", "48s")],
    5: [("camera_index", "H"), ("kind", "B"), ("bytes_per_pixel", "B"), ("image_id", "I"), ("camera_frame", "Q"),
        ("x0", "H"), ("y0", "H"), ("width", "H"), ("height", "H"), ("offset", "I"), ("total_bytes", "I"),
        ("chunk_len", "H"), (None, "H")],
    0x10: [("camera_index", "H"), ("n_clusters", "H"), ("seq", "I"), ("t_start_us", "Q"), ("t_end_us", "Q"),
           ("edge_done_ns", "Q"), ("trigger_frame", "d"), ("frame_period_us", "f"), ("syncs", "I")],
    0x11: [("camera_index", "H"), ("n_edges", "H"), ("seq", "I"), ("t_us", "Q"), ("edge_done_ns", "Q")],
    0x20: [("trigger_frame", "Q"), ("trigger_time", "d"), ("seq", "I"), ("n_objects", "H"), ("part_index", "B"),
           ("part_count", "B"), ("latency_ms", "f"), (None, "I")],
}
# Records: (array name, count field, fields).
RECORDS = {
    1: ("points", "n_points", [("x_dist", "f"), ("y_dist", "f"), ("x_undist", "f"), ("y_undist", "f"),
                               ("area", "f"), ("peak_diff", "f"), ("orientation", "f"), ("eccentricity", "f"),
                               ("cur_val", "H"), (None, "H"), ("mean_val", "f"), ("sumsq_val", "f")]),
    0x10: ("clusters", "n_clusters", [("id", "I"), ("x", "f"), ("y", "f"), ("vx", "f"), ("vy", "f"), ("size", "f"),
                                      ("mass", "f"), ("var_x", "f"), ("var_y", "f"), ("cov_xy", "f")]),
    0x11: ("edges", "n_edges", [("edge_id", "B"), (None, "3s"), ("angle", "f"), ("amplitude", "f"),
                                ("frequency", "f"), ("phase", "f")]),
    0x20: ("objects", "n_objects", [("obj_id", "I"), ("x", "f"), ("y", "f"), ("z", "f"), ("vx", "f"), ("vy", "f"),
                                    ("vz", "f")] + [(f"cov[{k}]", "f") for k in range(6)]),
}
SIZES = {"FIXED": {1: 56, 2: 144, 3: 40, 4: 56, 5: 36, 0x10: 48, 0x11: 24, 0x20: 32},
         "RECORD": {1: 44, 0x10: 40, 0x11: 20, 0x20: 52}}


def _layouts_match_the_spec_sizes() -> None:
    for t, fields in FIXED.items():
        assert struct.calcsize("<" + "".join(c for _, c in fields)) == SIZES["FIXED"][t], t
    for t, (_, _, fields) in RECORDS.items():
        assert struct.calcsize("<" + "".join(c for _, c in fields)) == SIZES["RECORD"][t], t


def _text(v: str, size: int) -> bytes:
    raw = re.sub(rb"\\x([0-9a-f]{2})", lambda m: bytes([int(m.group(1), 16)]), v.encode())
    assert len(raw) <= size
    return raw + b"\0" * (size - len(raw))


def _value(code: str, v: str):  # noqa: ANN202
    if code.endswith("s"):
        return _text(v, int(code[:-1]))
    if code in "fd":
        return float(v)  # "nan", "inf" and %.9g / %.17g all parse
    return int(v)


def _pack(fields: list, values: dict[str, str], prefix: str = "") -> tuple[bytes, str]:
    fmt, args = "<", []
    for name, code in fields:
        fmt += code
        if name is None:
            args.append(b"\0" * int(code[:-1]) if code.endswith("s") else 0)
        else:
            args.append(_value(code, values.pop(prefix + name)))
    return struct.pack(fmt, *args), fmt


def _encode(canon: str) -> tuple[bytes, list[str]]:
    """The datagram from its canonical fields, and the struct formats of its parts (for comparing)."""
    values = dict(kv.split("=", 1) for kv in canon.split(" "))
    t, flags = int(values.pop("type")), int(values.pop("flags"))
    fixed, f0 = _pack(FIXED[t], values)
    body, fmts = fixed, [f0]
    if t in RECORDS:
        arr, count, fields = RECORDS[t]
        n = int(dict(kv.split("=", 1) for kv in canon.split(" "))[count])
        for i in range(n):
            rec, fr = _pack(fields, values, f"{arr}[{i}].")
            body += rec
            fmts.append(fr)
    if t == 5:
        body += bytes.fromhex(values.pop("data"))
    assert not values, f"fields the SPEC tables do not have: {sorted(values)}"
    return b"FT" + struct.pack("<BBHH", 2, t, len(body), flags) + body, fmts


def _same_values(a: bytes, b: bytes, fmts: list[str]) -> bool:
    if a[:8] != b[:8]:
        return False
    off = 8
    for fmt in fmts:
        n = struct.calcsize(fmt)
        va, vb = struct.unpack_from(fmt, a, off), struct.unpack_from(fmt, b, off)
        for x, y in zip(va, vb, strict=True):
            if isinstance(x, float) and math.isnan(x):
                if not math.isnan(y):
                    return False
            elif x != y:
                return False
        off += n
    return a[off:] == b[off:]


def _valid(family: str) -> list[tuple[str, str, str]]:
    out = []
    for line in (VEC / f"{family}.tsv").read_text().splitlines():
        if line.startswith("valid\t"):
            _, name, hx, canon = line.split("\t", 3)
            out.append((name, hx, canon))
    return out


FAMILIES = ["features", "status", "control", "control_ack", "image", "dvs_clusters", "dvs_wingbeat",
            "live_estimates"]


def test_layouts_add_up_to_the_spec_sizes() -> None:
    _layouts_match_the_spec_sizes()


@pytest.mark.parametrize("family", FAMILIES)
def test_valid_vectors_equal_an_independent_encoding(family: str) -> None:
    vectors = _valid(family)
    assert vectors, family
    bytewise = 0
    for name, hx, canon in vectors:
        want = bytes.fromhex(hx)
        got, fmts = _encode(canon)
        if got == want:
            bytewise += 1
            continue
        assert "nan" in canon and _same_values(got, want, fmts), f"{family}/{name}:\n{got.hex()}\n{hx}"
    assert bytewise >= len(vectors) - 1, (family, bytewise, len(vectors))
