"""Trigger / sync events' times out of event files (ft_ev_triggers through EventReader(triggers=True)
and read_events_and_triggers): EVT 2.0 as the simulated DVS writes it, EVT 3.0, AEDAT 2.0 and 3.1
written here byte by byte as their formats define them."""

from __future__ import annotations

import struct

import numpy as np

from flytrack_host.dvs.events import (
    TRIGGER_DTYPE,
    EventReader,
    read_events,
    read_events_and_triggers,
)
from flytrack_host.sim.dvs import EV_DTYPE, Evt2Encoder, evt2_header


def _evt2_stream(n_periods: int = 300, seed: int = 0) -> tuple[bytes, np.ndarray, np.ndarray]:
    """EVT 2.0 bytes with events and one sync per period; (bytes, events, sync times)."""
    rng = np.random.default_rng(seed)
    enc = Evt2Encoder()
    parts = [evt2_header(346, 260)]
    evs, syncs = [], []
    t = 5_000_000
    for _ in range(n_periods):
        n = int(rng.integers(0, 400))
        ev = np.empty(n, EV_DTYPE)
        ev["t"] = np.sort(t + rng.integers(0, 9_990, n))
        ev["x"], ev["y"], ev["p"] = rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n)
        t += 10_000 + int(rng.integers(-3, 4))
        parts.append(enc.encode(ev, sync_us=t))
        evs.append(ev)
        syncs.append(t)
    return b"".join(parts), np.concatenate(evs), np.asarray(syncs, np.int64)


def test_evt2_sync_times_in_chunks_and_whole(tmp_path):
    data, ev, syncs = _evt2_stream()
    path = tmp_path / "s.raw"
    path.write_bytes(data)
    got_ev, trig = read_events_and_triggers(path)
    assert trig.dtype == TRIGGER_DTYPE
    np.testing.assert_array_equal(trig["t"], syncs)
    assert np.all(trig["value"] == 1) and np.all(trig["channel"] == 0)
    np.testing.assert_array_equal(got_ev["t"], ev["t"])
    np.testing.assert_array_equal(read_events(path)["x"], ev["x"])  # the plain reader is unchanged
    # In small chunks: each sync comes out with (or before) the chunk that passes its time.
    parts = []
    with EventReader(path, triggers=True, chunk=100) as r:
        for chunk in r:
            tr = r.read_triggers()
            parts.append(tr)
            if len(tr):
                assert tr["t"][-1] <= chunk["t"][-1] + 10_010
        parts.append(r.read_triggers())
        assert r.info.n_triggers == len(syncs)
    np.testing.assert_array_equal(np.concatenate(parts)["t"], syncs)
    # Not asked for: counted, not kept.
    with EventReader(path) as r:
        for _ in r:
            assert len(r.read_triggers()) == 0
        assert r.info.n_triggers == len(syncs)


def test_evt3_aedat2_aedat3_trigger_times(tmp_path):
    # EVT 3.0: TIME_HIGH 3, TIME_LOW 0x123, an event, EXT_TRIGGER channel 2 falling then rising.
    w16 = [0x8000 | 3, 0x6000 | 0x123, 0x0000 | 7, 0x2000 | 0x800 | 9, 0xA000 | (2 << 8) | 0,
           0x6000 | 0x200, 0xA000 | (2 << 8) | 1]
    p = tmp_path / "a.raw"
    p.write_bytes(b"% evt 3.0\n% geometry 640x480\n% end\n" + struct.pack(f"<{len(w16)}H", *w16))
    ev, tr = read_events_and_triggers(p)
    assert len(ev) == 1 and ev["t"][0] == (3 << 12) | 0x123
    assert tr["t"].tolist() == [(3 << 12) | 0x123, (3 << 12) | 0x200]
    assert tr["value"].tolist() == [0, 1] and tr["channel"].tolist() == [2, 2]
    # AEDAT 2.0 (DVS128): big-endian address, timestamp; bit 15 of the address = external sync.
    recs = [((5 << 8) | (10 << 1), 1000), (0x8000, 1500), ((7 << 8), 2000), (0x8000, 2500)]
    p2 = tmp_path / "b.aedat"
    p2.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: DVS128\r\n" + b"".join(struct.pack(">II", a, t) for a, t in recs))
    ev, tr = read_events_and_triggers(p2)
    assert ev["t"].tolist() == [1000, 2000] and tr["t"].tolist() == [1500, 2500]
    # AEDAT 3.1: a special-event packet (type 0) with a rising edge (kind 2) and a falling one (3),
    # timestamps with the packet's overflow above bit 31.
    def packet(typ: int, overflow: int, words: list[tuple[int, int]]) -> bytes:
        head = struct.pack("<hhiiiiii", typ, 1, 8, 4, overflow, len(words), len(words), len(words))
        return head + b"".join(struct.pack("<Ii", d, t) for d, t in words)

    p3 = tmp_path / "c.aedat"
    p3.write_bytes(b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DVS128\r\n#!END-HEADER\r\n"
                   + packet(1, 0, [((3 << 17) | (4 << 2) | 2 | 1, 90)])
                   + packet(0, 1, [((2 << 1) | 1, 100), ((3 << 1) | 1, 200), ((3 << 1) | 0, 300)]))
    ev, tr = read_events_and_triggers(p3)
    assert len(ev) == 1 and ev["t"][0] == 90
    assert tr["t"].tolist() == [(1 << 31) + 100, (1 << 31) + 200]  # the invalid one (bit 0 clear) skipped
    assert tr["value"].tolist() == [1, 0]


def test_aedat4_trigger_stream_written_by_dv_processing(tmp_path):
    """dv-processing writes triggers as their own stream (TriggerPacket, identifier TRIG): kept ones
    come out with their type's edge; the events of the event stream are unchanged."""
    import dv_processing as dv

    for comp in ("NONE", "LZ4", "ZSTD"):
        cfg = dv.io.MonoCameraWriter.Config("DVXplorer")
        cfg.addEventStream((346, 260))
        cfg.addTriggerStream()
        cfg.compression = getattr(dv.CompressionType, comp)
        path = tmp_path / f"t_{comp}.aedat4"
        w = dv.io.MonoCameraWriter(str(path), cfg)
        times = []
        for k in range(20):
            st = dv.EventStore()
            for t in range(10_000 * k, 10_000 * k + 9_000, 300):
                st.push_back(t, 5 + k, 6, bool(k % 2))
            w.writeEvents(st)
            tp = dv.TriggerPacket()
            tp.elements.append(dv.Trigger(10_000 * k + 9_500, dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE))
            tp.elements.append(dv.Trigger(10_000 * k + 9_700, dv.TriggerType.EXTERNAL_SIGNAL_FALLING_EDGE))
            tp.elements.append(dv.Trigger(10_000 * k + 9_800, dv.TriggerType.APS_FRAME_START))  # not a sync
            w.writeTriggerPacket(tp)
            times += [10_000 * k + 9_500, 10_000 * k + 9_700]
        del w
        ev, tr = read_events_and_triggers(path)
        assert len(ev) == 20 * 30 and ev["x"][-1] == 24
        assert tr["t"].tolist() == times, comp
        assert tr["value"].tolist() == [1, 0] * 20
        np.testing.assert_array_equal(read_events(path)["t"], ev["t"])  # without keeping: the same events
