"""Event files through libflytrack_events, cross-checked event for event against independent
readers and writers from PyPI: dv-processing and aedat (AEDAT 4.0), expelliarmus (EVT 2.0, EVT 3.0,
DAT). Plus streaming in small chunks, truncated and corrupt files (every event before the damage
kept, the error names the offset)."""

from __future__ import annotations

from pathlib import Path

import aedat
import dv_processing as dv
import numpy as np
import pytest
from expelliarmus import Wizard

from flytrack_host.dvs.events import (
    EVENT_DTYPE,
    EventFileError,
    EventReader,
    EventWriter,
    read_events,
    write_events,
)

W, H = 346, 260


def synthetic(n: int, seed: int = 0, t0: int = 1000, max_dt: int = 40, big_gaps: bool = False) -> np.ndarray:
    """Time-ordered events with repeats of the same time, both polarities, full sensor range."""
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    dt = rng.integers(0, max_dt, n)
    if big_gaps:  # past EVT 3.0's 24-bit and EVT 2.0's 34-bit... at least past 2^24 us
        dt[rng.integers(0, n, 5)] += 20_000_000
    ev["t"] = t0 + np.cumsum(dt)
    ev["x"] = rng.integers(0, W, n)
    ev["y"] = rng.integers(0, H, n)
    ev["p"] = rng.integers(0, 2, n)
    return ev


def same(a: np.ndarray, b: np.ndarray, pol: str = "p") -> None:
    assert len(a) == len(b)
    np.testing.assert_array_equal(a["t"].astype(np.int64), b["t"].astype(np.int64))
    np.testing.assert_array_equal(a["x"].astype(np.int64), b["x"].astype(np.int64))
    np.testing.assert_array_equal(a["y"].astype(np.int64), b["y"].astype(np.int64))
    np.testing.assert_array_equal(a["p"].astype(np.int64), b[pol].astype(np.int64))


def dv_read(path: Path) -> np.ndarray:
    rec = dv.io.MonoCameraRecording(str(path))
    parts = []
    while rec.isRunning():
        batch = rec.getNextEventBatch()
        if batch is None:
            break
        parts.append(batch.numpy())
    arr = np.concatenate(parts)
    out = np.empty(len(arr), EVENT_DTYPE)
    out["t"], out["x"], out["y"], out["p"] = arr["timestamp"], arr["x"], arr["y"], arr["polarity"]
    return out


def aedat_read(path: Path) -> np.ndarray:
    parts = [p["events"] for p in aedat.Decoder(str(path)) if "events" in p]
    arr = np.concatenate(parts)
    out = np.empty(len(arr), EVENT_DTYPE)
    out["t"], out["x"], out["y"], out["p"] = arr["t"], arr["x"], arr["y"], arr["on"]
    return out


def expelliarmus_read(path: Path, enc: str) -> np.ndarray:
    arr = Wizard(encoding=enc, fpath=str(path)).read()
    out = np.empty(len(arr), EVENT_DTYPE)
    out["t"], out["x"], out["y"], out["p"] = arr["t"], arr["x"], arr["y"], arr["p"]
    return out


def expelliarmus_write(path: Path, ev: np.ndarray, enc: str) -> None:
    arr = np.empty(len(ev), np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")]))
    arr["t"], arr["x"], arr["y"], arr["p"] = ev["t"], ev["x"], ev["y"], ev["p"]
    Wizard(encoding=enc).save(str(path), arr)


@pytest.mark.parametrize("compression", ["NONE", "LZ4", "ZSTD"])
def test_aedat4_written_by_dv_processing(tmp_path: Path, compression: str) -> None:
    ev = synthetic(30_000, seed=1)
    path = tmp_path / "dv.aedat4"
    cfg = dv.io.MonoCameraWriter.EventOnlyConfig("DVXplorer_test", (W, H))
    cfg.compression = getattr(dv.CompressionType, compression)
    writer = dv.io.MonoCameraWriter(str(path), cfg)
    for part in np.array_split(ev, 7):  # several packets
        store = dv.EventStore()
        for t, x, y, p in part[["t", "x", "y", "p"]].tolist():
            store.push_back(t, x, y, bool(p))
        writer.writeEvents(store)
    del writer  # dv writes its data table on destruction
    ours = read_events(path)
    same(ours, ev)
    same(ours, dv_read(path))
    same(ours, aedat_read(path))
    with EventReader(path) as r:
        assert (r.info.format, r.info.width, r.info.height) == ("aedat4", W, H)
        assert r.info.compression == compression.lower()


@pytest.mark.parametrize("compression", ["none", "lz4", "zstd", "zstd_high"])
def test_aedat4_written_by_us_reads_in_dv_processing_and_aedat(tmp_path: Path, compression: str) -> None:
    ev = synthetic(80_000, seed=2, big_gaps=True)  # > one 32768-event packet
    path = tmp_path / "ours.aedat4"
    with EventWriter(path, W, H, compression=compression) as w:
        w.write(ev[:1000])
        with pytest.raises(ValueError, match="back in time"):
            w.write(ev[:10])  # refused, nothing written, the writer goes on
        w.write(ev[1000:])
    same(dv_read(path), ev)
    same(aedat_read(path), ev)
    same(read_events(path), ev)
    assert dv.io.MonoCameraRecording(str(path)).getEventResolution() == (W, H)


def test_evt2_written_by_expelliarmus(tmp_path: Path) -> None:
    ev = synthetic(50_000, seed=3, big_gaps=True)
    path = tmp_path / "x.raw"
    expelliarmus_write(path, ev, "EVT2")
    ours = read_events(path)
    same(ours, ev)
    same(ours, expelliarmus_read(path, "EVT2"))


def test_evt3_written_by_us_reads_in_expelliarmus(tmp_path: Path) -> None:
    ev = synthetic(50_000, seed=4, big_gaps=True)
    path = tmp_path / "ours.raw"
    write_events(path, ev, W, H)  # .raw -> EVT 3.0
    same(read_events(path), ev)
    theirs = expelliarmus_read(path, "EVT3")
    # Every event's address and polarity agree. Times: expelliarmus 1.1.12 adds a 4096 us step both
    # for a TIME_HIGH word and for a TIME_LOW lower than the previous one, so it counts most
    # TIME_HIGH steps twice on spec streams (TIME_HIGH then TIME_LOW, as sensors send them). Its
    # times agree until the first such step and differ from ours only in whole 4096 us steps after.
    assert len(theirs) == len(ev)
    for k in ("x", "y", "p"):
        np.testing.assert_array_equal(theirs[k], ev[k])
    first_step = int(np.argmax(ev["t"] >= 4096))
    np.testing.assert_array_equal(theirs["t"][:first_step], ev["t"][:first_step])
    assert np.all((theirs["t"] - ev["t"]) % 4096 == 0)
    with EventReader(path) as r:
        assert (r.info.format, r.info.width, r.info.height) == ("evt3", W, H)


def test_evt3_vector_words_read_by_expelliarmus(tmp_path: Path) -> None:
    # runs along a row at one time (an edge crossing the sensor) go out as VECT_BASE_X + VECT_12;
    # within the first 4096 us expelliarmus' times are exact (see above), so every field is compared
    rng = np.random.default_rng(11)
    parts = []
    for t in range(0, 4000, 4):
        n = int(rng.integers(1, 9))
        x0 = int(rng.integers(0, W - 12))
        xs = np.sort(rng.choice(12, n, replace=False)) + x0
        run = np.empty(n, EVENT_DTYPE)
        run["t"], run["x"], run["y"], run["p"] = t, xs, rng.integers(0, H), rng.integers(0, 2)
        parts.append(run)
    ev = np.concatenate(parts)
    path = tmp_path / "vec.raw"
    write_events(path, ev, W, H)
    words = np.frombuffer(path.read_bytes().split(b"% end\n", 1)[1], "<u2")
    assert np.count_nonzero(words >> 12 == 0x4) > 500  # VECT_12 words were written
    same(read_events(path), ev)
    same(expelliarmus_read(path, "EVT3"), ev)


def test_evt3_written_by_expelliarmus(tmp_path: Path) -> None:
    # expelliarmus 1.1.12's EVT 3.0 writer emits no TIME_HIGH word after the first (its own reader
    # then loses the high bits too), so its files are compared within the first 4096 us.
    ev = synthetic(3_000, seed=5, t0=0, max_dt=2)
    ev = ev[ev["t"] < 4096]
    path = tmp_path / "x.raw"
    expelliarmus_write(path, ev, "EVT3")
    ours = read_events(path)
    same(ours, ev)
    same(ours, expelliarmus_read(path, "EVT3"))


def test_dat_written_by_expelliarmus(tmp_path: Path) -> None:
    ev = synthetic(50_000, seed=6)
    path = tmp_path / "x.dat"
    expelliarmus_write(path, ev, "DAT")
    ours = read_events(path)
    same(ours, ev)
    same(ours, expelliarmus_read(path, "DAT"))


def test_small_chunks_stream_the_same_events(tmp_path: Path) -> None:
    ev = synthetic(20_000, seed=7)
    path = tmp_path / "s.aedat4"
    write_events(path, ev, W, H, compression="lz4")
    with EventReader(path, chunk=100) as r:
        chunks = list(r)
        assert r.info.n_events == len(ev)
    assert max(len(c) for c in chunks) <= 100
    same(np.concatenate(chunks), ev)


@pytest.mark.parametrize(("suffix", "unit"), [(".aedat4", 0), (".raw", 2), ("evt2.raw", 4), (".dat", 8)])
def test_truncated_files_keep_every_event_before_the_cut(tmp_path: Path, suffix: str, unit: int) -> None:
    ev = synthetic(150_000, seed=8)
    path = tmp_path / f"t{suffix}"
    if suffix == "evt2.raw":
        expelliarmus_write(path, ev, "EVT2")
    elif suffix == ".dat":
        expelliarmus_write(path, ev, "DAT")
    else:
        write_events(path, ev, W, H)
    data = path.read_bytes()
    full = read_events(path)
    with EventReader(path) as r:
        header = r.info.offset  # bytes of header consumed on open
    rng = np.random.default_rng(9)
    for cut in sorted(rng.integers(header + 1, len(data) - 1, 5)):
        if unit and (cut - header) % unit == 0:
            cut += 1  # inside a word, not between two
        bad = tmp_path / f"cut{suffix}"
        bad.write_bytes(data[:cut])
        with pytest.raises(EventFileError, match=r"truncated file") as info:
            read_events(bad)
        exc = info.value
        assert exc.offset is not None and header <= exc.offset < cut
        assert f"at byte {exc.offset}" in str(exc)
        kept = exc.events
        same(kept, full[: len(kept)])  # nothing invented, in order
        # nothing lost that was whole before the damage: the file cut at the damaged unit's offset
        # (a word or packet boundary) reads cleanly to exactly the events kept
        clean = tmp_path / f"clean{suffix}"
        clean.write_bytes(data[:exc.offset])
        same(read_events(clean), kept)
        assert cut - exc.offset < (unit or len(data))


def test_corrupt_aedat4_packet_names_its_offset(tmp_path: Path) -> None:
    ev = synthetic(100_000, seed=10)
    path = tmp_path / "c.aedat4"
    write_events(path, ev, W, H, compression="lz4")
    data = bytearray(path.read_bytes())
    # the second packet: walk the headers (i32 stream, i32 size) after the IOHeader
    pos = 14 + 4 + int.from_bytes(data[14:18], "little")
    first_size = int.from_bytes(data[pos + 4:pos + 8], "little")
    second = pos + 8 + first_size
    data[second + 8 + 20] ^= 0xFF  # inside its LZ4 frame
    path.write_bytes(bytes(data))
    with pytest.raises(EventFileError) as info:
        read_events(path)
    assert info.value.offset == second
    same(info.value.events, ev[:32768])


def test_unknown_and_missing_files(tmp_path: Path) -> None:
    with pytest.raises(EventFileError, match="cannot open"):
        EventReader(tmp_path / "nope.aedat4")
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"not an event file at all")
    with pytest.raises(EventFileError, match="unknown event file format"):
        read_events(junk)
    with pytest.raises(ValueError, match="unknown event file format 'evt4'"):
        read_events(junk, fmt="evt4")
    # a headerless EVT 2.0 stream is read when the format is named
    raw = np.array([0x80000001, (1 << 28) | (3 << 22) | (5 << 11) | 7], "<u4").tobytes()
    with EventReader(raw, fmt="evt2") as r:
        got = np.concatenate(list(r))
    assert got.tolist() == [(67, 5, 7, 1)]
