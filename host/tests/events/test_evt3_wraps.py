"""EVT 3.0 written here, across many 2^24 us wraps of its time, read by decoders that follow
Prophesee's reference decoding: the `evt3` package from PyPI, and a small decoder written below from
the format description alone.

EVT 3.0 carries 24 bits of time: TIME_HIGH (type 0x8) the upper 12, TIME_LOW (0x6) the lower 12, so
the time wraps every 2^24 us (16.8 s) and a reader must count the wraps itself. Prophesee's reference
decoder (its EVT 3.0 decoding sample) counts one when a TIME_HIGH falls back by at least
(4095 - 10) x 4096 us below the previous one, i.e. only a step from the top of the range to its
bottom, as a camera sends it; the HAL's decoder asks for a fall of at least half the range. A file
must mark each wrap in a way every such reader counts."""

from __future__ import annotations

from pathlib import Path

import evt3
import numpy as np
import pytest

from flytrack_host.dvs.events import EVENT_DTYPE, read_events, write_events

W, H = 640, 480
MAX_BASE = 4095  # the largest TIME_HIGH value, in 4096 us steps


def reference_decode(data: bytes, loop_threshold_steps: int) -> np.ndarray:
    """(t, x, y, p) of every CD event (ADDR_X and vectors), counting a time-high wrap when a
    TIME_HIGH falls at least MAX_BASE - loop_threshold_steps below the previous one."""
    words = np.frombuffer(data.split(b"% end\n", 1)[1], "<u2")
    out = []
    loops = 0
    high = low = y = base_x = pol = 0
    have_high = False
    for w in map(int, words):
        kind, v = w >> 12, w & 0xFFF
        if kind == 0x8:
            if have_high and high - v >= MAX_BASE - loop_threshold_steps:
                loops += 1
            high, have_high = v, True
        elif kind == 0x6:
            low = v
        elif kind == 0x0:
            y = v & 0x7FF
        elif kind == 0x2:
            out.append(((loops << 24) | (high << 12) | low, v & 0x7FF, y, v >> 11))
        elif kind == 0x3:
            base_x, pol = v & 0x7FF, v >> 11
        elif kind in (0x4, 0x5):
            bits = 12 if kind == 0x4 else 8
            for b in range(bits):
                if (v >> b) & 1:
                    out.append(((loops << 24) | (high << 12) | low, base_x + b, y, pol))
            base_x += bits
    return np.array(out, dtype=np.int64).reshape(-1, 4)


def spanning_wraps(seed: int = 0) -> np.ndarray:
    """About 100 s of events: a steady stream (one every few ms, so every TIME_HIGH step is small),
    quiet spells of a few seconds, and a gap of 40 s (more than two wraps with no event)."""
    rng = np.random.default_rng(seed)
    dt = rng.integers(0, 25_000, 6000)
    dt[rng.integers(0, len(dt), 6)] += 5_000_000
    dt[3000] += 40_000_000
    ev = np.empty(len(dt), EVENT_DTYPE)
    ev["t"] = 123 + np.cumsum(dt)
    ev["x"], ev["y"], ev["p"] = rng.integers(0, W, len(dt)), rng.integers(0, H, len(dt)), rng.integers(0, 2, len(dt))
    return ev


def rows(ev: np.ndarray) -> np.ndarray:
    return np.stack([ev["t"], ev["x"], ev["y"], ev["p"]], axis=1).astype(np.int64)


def test_the_file_spans_several_wraps() -> None:
    ev = spanning_wraps()
    assert ev["t"][-1] >> 24 >= 5


@pytest.mark.parametrize(("rule", "threshold"), [("Prophesee's decoding sample", 10), ("openeb HAL", 2047)])
def test_every_wrap_is_counted_by_the_reference_rules(tmp_path: Path, rule: str, threshold: int) -> None:
    ev = spanning_wraps()
    path = tmp_path / "w.raw"
    write_events(path, ev, W, H)
    np.testing.assert_array_equal(reference_decode(path.read_bytes(), threshold), rows(ev), err_msg=rule)
    np.testing.assert_array_equal(rows(read_events(path)), rows(ev))  # and by ours


def test_evt3_from_pypi_reads_the_same_times(tmp_path: Path) -> None:
    ev = spanning_wraps(seed=1)
    path = tmp_path / "w.raw"
    write_events(path, ev, W, H)
    theirs = evt3.decode_file(str(path))
    assert (theirs.sensor_width, theirs.sensor_height) == (W, H)
    got = np.stack([theirs.t, theirs.x, theirs.y, theirs.p], axis=1).astype(np.int64)
    np.testing.assert_array_equal(got, rows(ev))


def test_an_event_on_each_side_of_a_wrap(tmp_path: Path) -> None:
    # the smallest cases: the last step of a range to the first of the next, and a jump of exactly
    # one range, of one range and a step, of many ranges
    for ts in ([2**24 - 1, 2**24], [2**24 - 4096, 2**24 + 4096], [5, 5 + 2**24], [7, 7 + 2**24 + 4096],
               [100, 100 + 9 * 2**24 + 12345]):
        ev = np.zeros(len(ts), EVENT_DTYPE)
        ev["t"], ev["x"], ev["y"] = ts, [3, 4], [5, 6]
        path = tmp_path / "e.raw"
        write_events(path, ev, W, H)
        for threshold in (10, 2047):
            np.testing.assert_array_equal(reference_decode(path.read_bytes(), threshold)[:, 0], ts)
        np.testing.assert_array_equal(evt3.decode_file(str(path)).t.astype(np.int64), ts)
        np.testing.assert_array_equal(read_events(path)["t"], ts)
