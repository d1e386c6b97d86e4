"""`flytrack events info` and `flytrack events convert`: conversions checked against dv-processing
reading the result, damaged inputs converted up to the damage with exit 2 and the offset named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.dvs.events import EVENT_DTYPE, read_events, write_events

from .test_files import dv_read, expelliarmus_write, same


def run(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(app, ["events", *args])
    return r.exit_code, " ".join(r.output.split())  # rich wraps long lines


def _events(n: int) -> np.ndarray:
    rng = np.random.default_rng(3)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = 100 + np.cumsum(rng.integers(0, 5, n))
    ev["x"], ev["y"], ev["p"] = rng.integers(0, 304, n), rng.integers(0, 240, n), rng.integers(0, 2, n)
    return ev


def test_convert_dat_to_aedat4_and_evt3(tmp_path: Path) -> None:
    ev = _events(30_000)
    src = tmp_path / "in.dat"
    expelliarmus_write(src, ev, "DAT")  # no sensor size in expelliarmus' DAT header
    rc, out = run("convert", str(src), str(tmp_path / "out.aedat4"))
    assert rc == 2 and "--width and --height" in out
    rc, out = run("convert", str(src), str(tmp_path / "out.aedat4"), "--width", "304", "--height", "240",
                  "--compression", "zstd")
    assert rc == 0, out
    assert "30,000 events" in out
    same(dv_read(tmp_path / "out.aedat4"), ev)
    rc, out = run("convert", str(tmp_path / "out.aedat4"), str(tmp_path / "out.raw"))
    assert rc == 0, out
    same(read_events(tmp_path / "out.raw"), ev)
    rc, out = run("info", str(tmp_path / "out.raw"))
    assert rc == 0 and "evt3" in out and "sensor 304x240" in out
    assert f"{int(ev['p'].sum()):,} ON" in out


def test_damaged_input_converts_up_to_the_damage(tmp_path: Path) -> None:
    ev = _events(50_000)
    src = tmp_path / "in.raw"
    write_events(src, ev, 304, 240)
    data = src.read_bytes()
    cut = tmp_path / "cut.raw"
    cut.write_bytes(data[: len(data) // 2 + 1])
    rc, out = run("info", str(cut))
    assert rc == 2 and "truncated file" in out and "at byte" in out
    rc, out = run("convert", str(cut), str(tmp_path / "saved.aedat4"))
    assert rc == 2 and "truncated file" in out
    saved = read_events(tmp_path / "saved.aedat4")
    assert len(saved) > 0
    same(saved, ev[: len(saved)])
    assert f"the {len(saved):,} events before it were converted" in out
    rc, out = run("info", str(tmp_path / "nope.aedat4"))
    assert rc == 2 and "cannot open" in out
