"""AEDAT 2.0 files from DAVIS cameras, built here word by word from jAER's DAVIS address layout
(eu.seebetter.ini.chips.DavisChip and DavisBaseCamera's event extractor), not from any reader:

- bit 31 clear: a DVS word; its bits 11..10 = 01 mark an external input event (a trigger), otherwise
  it is a polarity event with y in bits 30..22, x in bits 21..12 (mirrored: x = width - 1 - field),
  polarity in bit 11 (1 = ON);
- bit 31 set with bits 11..10 = 11 (0x80000C00 all set): an IMU sample word;
- bit 31 set otherwise: an APS (frame) ADC sample.

The chip, and so the layout and sensor size, is named by the header's `# AEChip:` line."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.dvs.events import EventFileError, EventReader, read_events, read_events_and_triggers

HEADER = ("#!AER-DAT2.0\r\n# This is a raw AE data file - do not edit\r\n"
          "# Data format is int32 address, int32 timestamp (8 bytes total), repeated for each event\r\n"
          "# Timestamps tick is 1 us\r\n# AEChip: {chip}\r\n# created Mon Jan 01 12:00:00 CET 2018\r\n")


def dvs_word(x_field: int, y: int, on: int) -> int:
    return (y << 22) | (x_field << 12) | (on << 11)


def aps_word(x: int, y: int, readcycle: int, adc: int) -> int:
    return 0x80000000 | (y << 22) | (x << 12) | (readcycle << 10) | adc


def imu_word(code: int, value: int) -> int:
    # the IMU type bits (31, 11, 10) are set in every word of a sample; the sample type code and the
    # 16-bit value sit in other bits, which a DVS decoder must never look at
    return 0x80000C00 | (code << 28) | (value << 12)


EXTERNAL = 0x400  # bit 31 clear, bits 11..10 = 01


def davis_file(path: Path, chip: str, width: int, height: int, n: int = 3000, seed: int = 0):
    """A DAVIS recording: DVS events mixed with APS frame samples, IMU samples (7 words each) and
    external input events; returns (expected events as (t, x, y, p) rows, trigger times, words
    that are neither)."""
    rng = np.random.default_rng(seed)
    recs: list[tuple[int, int]] = []
    expected, triggers = [], []
    other = 0
    t = 1000
    for _ in range(n):
        t += int(rng.integers(0, 30))
        kind = rng.random()
        if kind < 0.6:
            xf, y, on = int(rng.integers(0, width)), int(rng.integers(0, height)), int(rng.integers(0, 2))
            recs.append((dvs_word(xf, y, on), t))
            expected.append((t, width - 1 - xf, y, on))
        elif kind < 0.8:
            recs.append((aps_word(int(rng.integers(0, width)), int(rng.integers(0, height)),
                                  int(rng.integers(0, 2)), int(rng.integers(0, 1024))), t))
            other += 1
        elif kind < 0.95:
            for code in range(7):  # accel x, y, z, temperature, gyro x, y, z at one time
                recs.append((imu_word(code, int(rng.integers(0, 1 << 16))), t))
            other += 7
        else:
            recs.append((EXTERNAL, t))
            triggers.append(t)
    path.write_bytes(HEADER.format(chip=chip).encode() + b"".join(struct.pack(">II", a, ts) for a, ts in recs))
    return np.array(expected, dtype=np.int64), np.array(triggers, dtype=np.int64), other


@pytest.mark.parametrize(("chip", "size"), [
    ("eu.seebetter.ini.chips.davis.DAVIS240C", (240, 180)),
    ("eu.seebetter.ini.chips.davis.Davis346B", (346, 260)),
    ("eu.seebetter.ini.chips.davis.Davis346red", (346, 260)),
    ("eu.seebetter.ini.chips.davis.Davis640", (640, 480)),
    ("eu.seebetter.ini.chips.davis.Davis128", (128, 128)),
])
def test_davis_aedat2_decoded_with_the_chips_layout_and_size(tmp_path: Path, chip: str, size: tuple[int, int]) -> None:
    w, h = size
    path = tmp_path / "davis.aedat"
    expected, trig, other = davis_file(path, chip, w, h)
    ev, tr = read_events_and_triggers(path)
    got = np.stack([ev["t"], ev["x"], ev["y"], ev["p"]], axis=1).astype(np.int64)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(tr["t"], trig)
    assert np.all(tr["value"] == 1)
    with EventReader(path) as r:
        list(r)
        assert (r.info.format, r.info.width, r.info.height) == ("aedat2", w, h)
        assert r.info.n_triggers == len(trig)
        assert r.info.n_skipped == other  # APS and IMU words: not events, not triggers


def test_davis_events_span_the_whole_sensor_and_both_polarities(tmp_path: Path) -> None:
    # what a DVS128 reading of the same words gave: x always 127, every event ON, half of them triggers
    path = tmp_path / "d.aedat"
    expected, _, _ = davis_file(path, "eu.seebetter.ini.chips.davis.DAVIS240C", 240, 180, n=5000, seed=3)
    ev = read_events(path)
    assert ev["x"].max() > 200 and ev["y"].max() > 150
    assert 0.4 < ev["p"].mean() < 0.6
    assert len(ev) == len(expected)


@pytest.mark.parametrize("chip", ["eu.seebetter.ini.chips.davis.DavisRGBW640",
                                  "ch.unizh.ini.jaer.chip.cochlea.CochleaAMS1c",
                                  "eu.seebetter.ini.chips.davis.Davis208PixelParade"])
def test_a_chip_whose_layout_is_not_known_is_refused_by_name(tmp_path: Path, chip: str) -> None:
    path = tmp_path / "u.aedat"
    path.write_bytes(HEADER.format(chip=chip).encode() + struct.pack(">II", 0x1234, 10))
    with pytest.raises(EventFileError, match=r"AEChip .*" + chip.rsplit(".", 1)[1]) as info:
        read_events(path)
    assert "DVS128" in str(info.value) and "DAVIS" in str(info.value)  # says which chips are read


def test_dvs128_files_are_read_as_before(tmp_path: Path) -> None:
    recs = [((5 << 8) | (10 << 1) | 1, 1000), ((127 << 8) | (0 << 1), 2000)]
    for chip in ("ch.unizh.ini.jaer.chip.retina.DVS128", "DVS128", None):
        path = tmp_path / "a.aedat"
        head = "#!AER-DAT2.0\r\n" + (f"# AEChip: {chip}\r\n" if chip else "")
        path.write_bytes(head.encode() + b"".join(struct.pack(">II", a, t) for a, t in recs))
        ev = read_events(path)
        assert ev[["t", "x", "y", "p"]].tolist() == [(1000, 117, 5, 0), (2000, 127, 127, 1)]
        with EventReader(path) as r:
            assert (r.info.width, r.info.height) == (128, 128)
