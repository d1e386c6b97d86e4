"""`flytrack events convert` on recordings as their own tools write them: dv-processing's AEDAT 4.0
with Unix-epoch microsecond times (as DV records), and external trigger events in EVT 3.0 and AEDAT
4.0, read back by dv-processing, the `evt3` package and our own readers."""

from __future__ import annotations

import re
from pathlib import Path

import dv_processing as dv
import evt3
import numpy as np
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.dvs.events import EVENT_DTYPE, EventReader, read_events, read_events_and_triggers

W, H = 346, 260
EPOCH_US = 1_712_345_678_901_234  # 2024-04-05, as DV stamps its events


def run(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(app, ["events", *args])
    return r.exit_code, " ".join(r.output.split())  # rich wraps long lines


def dv_epoch_recording(path: Path, n: int = 112_000, seed: int = 0) -> np.ndarray:
    """An AEDAT 4.0 file as DV records one: Unix-epoch times, several packets."""
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = EPOCH_US + np.cumsum(rng.integers(0, 90, n))  # ~5 s
    ev["x"], ev["y"], ev["p"] = rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n)
    cfg = dv.io.MonoCameraWriter.EventOnlyConfig("DAVIS346_00000499", (W, H))
    writer = dv.io.MonoCameraWriter(str(path), cfg)
    for part in np.array_split(ev, 20):
        store = dv.EventStore()
        for t, x, y, p in part[["t", "x", "y", "p"]].tolist():
            store.push_back(t, x, y, bool(p))
        writer.writeEvents(store)
    del writer
    return ev


def test_epoch_times_are_rebased_into_a_small_evt3_file(tmp_path: Path) -> None:
    src = tmp_path / "dv.aedat4"
    ev = dv_epoch_recording(src)
    dst = tmp_path / "out.raw"
    rc, out = run("convert", str(src), str(dst))
    assert rc == 0, out
    # ~2 to 3 words an event: not hundreds of MB of TIME_HIGH padding up to the epoch
    assert dst.stat().st_size < 8 * len(ev), dst.stat().st_size
    head = dst.read_bytes()[:400].decode(errors="replace")
    m = re.search(r"^% time_offset_us (\d+)$", head, re.M)
    assert m, head
    offset = int(m.group(1))
    assert 0 < ev["t"][0] - offset < 2**24
    assert f"{offset:,}" in out or str(offset) in out  # the command says what it did
    # times come back right: ours with the offset added back, a reader that does not know the
    # header line (evt3 from PyPI) relative to it, and both in the same order as written
    back = read_events(dst)
    np.testing.assert_array_equal(back["t"], ev["t"])
    np.testing.assert_array_equal(back["x"], ev["x"])
    theirs = evt3.decode_file(str(dst))
    np.testing.assert_array_equal(theirs.t.astype(np.int64) + offset, ev["t"])
    with EventReader(dst) as r:
        assert r.info.time_offset == offset
    # and back to AEDAT 4.0: the epoch times again, as dv-processing reads them
    again = tmp_path / "again.aedat4"
    rc, out = run("convert", str(dst), str(again))
    assert rc == 0, out
    rec = dv.io.MonoCameraRecording(str(again))
    assert rec.getTimeRange()[0] == ev["t"][0]
    np.testing.assert_array_equal(rec.getNextEventBatch().timestamps()[:100], ev["t"][:100])


# ---- external triggers through convert ------------------------------------------------------------

def evt3_with_triggers(path: Path, channel: int = 0, n_periods: int = 200, seed: int = 2):
    """EVT 3.0 built word by word from the format description: events, and per period a rising and
    a falling EXT_TRIGGER edge (type 0xA: bits 11..8 the channel, bit 0 the value) at their own
    TIME_LOW. Returns (events, trigger times, trigger values)."""
    rng = np.random.default_rng(seed)
    words: list[int] = []
    evs, trig_t, trig_v = [], [], []
    t = 1000
    for _ in range(n_periods):
        for k in range(int(rng.integers(1, 20))):
            t += int(rng.integers(1, 200))
            x, y, p = int(rng.integers(0, W)), int(rng.integers(0, H)), int(rng.integers(0, 2))
            words += [0x8000 | (t >> 12) & 0xFFF, 0x6000 | (t & 0xFFF), y, 0x2000 | (p << 11) | x]
            evs.append((t, x, y, p))
            if k == 0:  # a rising edge at this event's time, the falling one 100 us later
                words.append(0xA000 | (channel << 8) | 1)
                trig_t.append(t)
                trig_v.append(1)
                t += 100
                words += [0x8000 | (t >> 12) & 0xFFF, 0x6000 | (t & 0xFFF), 0xA000 | (channel << 8)]
                trig_t.append(t)
                trig_v.append(0)
    assert t < 2**24
    path.write_bytes(f"% evt 3.0\n% format EVT3;height={H};width={W}\n% geometry {W}x{H}\n% end\n".encode()
                     + np.array(words, "<u2").tobytes())
    return np.array(evs, np.int64), np.array(trig_t, np.int64), np.array(trig_v, np.int64)


def dv_triggers(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Trigger times and dv TriggerType values as dv-processing reads them."""
    rec = dv.io.MonoCameraRecording(str(path))
    assert rec.isTriggerStreamAvailable()
    t, kind = [], []
    while True:
        batch = rec.getNextTriggerBatch()
        if batch is None:
            break
        for trig in batch:
            t.append(trig.timestamp)
            kind.append(int(trig.type))
    return np.array(t, np.int64), np.array(kind, np.int64)


def test_evt3_triggers_kept_in_aedat4_and_evt3(tmp_path: Path) -> None:
    src = tmp_path / "trig.raw"
    ev, tt, tv = evt3_with_triggers(src)
    # to AEDAT 4.0: a trigger stream dv-processing reads, rising edges as EXTERNAL_SIGNAL_RISING_EDGE
    a4 = tmp_path / "out.aedat4"
    rc, out = run("convert", str(src), str(a4))
    assert rc == 0, out
    assert f"{len(tt):,} triggers" in out
    got_t, got_kind = dv_triggers(a4)
    np.testing.assert_array_equal(got_t, tt)
    rising, falling = int(dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE), int(dv.TriggerType.EXTERNAL_SIGNAL_FALLING_EDGE)
    np.testing.assert_array_equal(got_kind, np.where(tv == 1, rising, falling))
    back = read_events(a4)
    np.testing.assert_array_equal(back["t"], ev[:, 0])  # the events unchanged beside them
    # to EVT 3.0: EXT_TRIGGER words the evt3 package reads, interleaved at their times
    raw = tmp_path / "out.raw"
    rc, out = run("convert", str(src), str(raw))
    assert rc == 0, out
    theirs_ev, theirs_tr = evt3.decode_file_with_triggers(str(raw))
    np.testing.assert_array_equal(theirs_tr.timestamp.astype(np.int64), tt)
    np.testing.assert_array_equal(theirs_tr.value.astype(np.int64), tv)
    np.testing.assert_array_equal(theirs_ev.t.astype(np.int64), ev[:, 0])
    _, ours = read_events_and_triggers(raw)
    np.testing.assert_array_equal(ours["t"], tt)
    # and AEDAT 4.0 -> EVT 3.0 -> AEDAT 4.0 keeps them too
    rc, out = run("convert", str(a4), str(tmp_path / "again.raw"))
    assert rc == 0, out
    _, again = read_events_and_triggers(tmp_path / "again.raw")
    np.testing.assert_array_equal(again["t"], tt)
    np.testing.assert_array_equal(again["value"], tv)


def test_dv_trigger_stream_kept_in_evt3(tmp_path: Path) -> None:
    cfg = dv.io.MonoCameraWriter.Config("DVXplorer")
    cfg.addEventStream((W, H))
    cfg.addTriggerStream()
    src = tmp_path / "dv.aedat4"
    w = dv.io.MonoCameraWriter(str(src), cfg)
    times, values = [], []
    for k in range(30):
        st = dv.EventStore()
        for t in range(10_000 * k, 10_000 * k + 9_000, 500):
            st.push_back(t, 5 + k, 6, bool(k % 2))
        w.writeEvents(st)
        tp = dv.TriggerPacket()
        tp.elements.append(dv.Trigger(10_000 * k + 9_500, dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE))
        tp.elements.append(dv.Trigger(10_000 * k + 9_700, dv.TriggerType.EXTERNAL_SIGNAL_FALLING_EDGE))
        tp.elements.append(dv.Trigger(10_000 * k + 9_800, dv.TriggerType.APS_FRAME_START))  # not external
        w.writeTriggerPacket(tp)
        times += [10_000 * k + 9_500, 10_000 * k + 9_700]
        values += [1, 0]
    del w
    dst = tmp_path / "out.raw"
    rc, out = run("convert", str(src), str(dst))
    assert rc == 0, out
    _, tr = evt3.decode_file_with_triggers(str(dst))
    np.testing.assert_array_equal(tr.timestamp.astype(np.int64), times)
    np.testing.assert_array_equal(tr.value.astype(np.int64), values)


def test_what_the_output_cannot_hold_is_said(tmp_path: Path) -> None:
    # AEDAT 4.0 triggers have no input channel: written, and the loss of the channel is said
    src = tmp_path / "ch.raw"
    _, tt, _ = evt3_with_triggers(src, channel=3, n_periods=20)
    rc, out = run("convert", str(src), str(tmp_path / "ch.aedat4"))
    assert rc == 0, out
    assert "channel" in out and "AEDAT 4.0" in out
    np.testing.assert_array_equal(dv_triggers(tmp_path / "ch.aedat4")[0], tt)
    # EVT 2.0 channels go to 31, EVT 3.0's to 15: a trigger on channel 20 cannot be written, and is counted
    words = [0x80000000, (0xA << 28) | (5 << 22) | (20 << 8) | 1, (0xA << 28) | (6 << 22) | (2 << 8) | 1,
             (1 << 28) | (7 << 22) | (5 << 11) | 7]
    src2 = tmp_path / "ch20.raw"
    src2.write_bytes(b"% evt 2.0\n% geometry 640x480\n% end\n" + np.array(words, "<u4").tobytes())
    rc, out = run("convert", str(src2), str(tmp_path / "ch20_out.raw"))
    assert rc == 0, out
    assert "1 trigger" in out and "channel 20" in out and "cannot" in out
    _, tr = read_events_and_triggers(tmp_path / "ch20_out.raw")
    assert tr[["t", "channel"]].tolist() == [(6, 2)]
