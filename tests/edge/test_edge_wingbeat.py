"""flytrack-edge --wingbeat 1 (plain and ASan + UBSan builds): an event file of a simulated tethered fly goes
out as DVS_WINGBEAT datagrams (protocol/SPEC.md 1.7), one per 5 ms of event time, records 0-1 the wings and 2-5
their edges once the fly is found; a file without a fly sends empty datagrams and says why, in the log and in
STATUS; bad wing-beat options are refused."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.dvs.events import EVENT_DTYPE, write_events
from flytrack_host.dvs.wingbeat.simulate import FlySimParams, simulate_tethered_fly
from flytrack_host.protocol import DvsClusters, DvsWingbeat, EdgeStatus

from .test_edge_events import run

SECONDS = 0.5


@pytest.fixture(scope="module")
def fly_file(tmp_path_factory) -> Path:
    ev, _ = simulate_tethered_fly(FlySimParams(duration_s=SECONDS, seed=3))
    path = tmp_path_factory.mktemp("wb") / "fly.aedat4"
    write_events(path, ev, width=128, height=128)
    return path


def test_wingbeat_mode_sends_wing_estimates(edge_any: Path, receiver, fly_file: Path, no_sanitizer_report) -> None:
    rc, err = run(edge_any, receiver, fly_file, "--wingbeat", "1", "--realtime", "0")
    no_sanitizer_report(err)
    assert rc == 0, err
    assert "fly found" in err and "0 of 1 initialisation windows found no fly" in err
    wb = [m for m in receiver.messages if isinstance(m, DvsWingbeat)]
    assert not [m for m in receiver.messages if isinstance(m, DvsClusters)]
    t = np.array([m.t_us for m in wb])
    assert len(wb) == pytest.approx(SECONDS / 0.005, abs=2)
    assert np.all(np.diff(t)[:-1] == 5000)  # a fixed grid of event time; the last one is the final flush
    found = [m for m in wb if m.n_edges]
    assert all(m.n_edges == 0 for m in wb if m.t_us < 100_000)  # the initialisation window
    assert len(found) >= len(wb) - 21 and all(m.n_edges == 6 for m in found)
    assert all(list(m.edges["edge_id"]) == [0, 1, 2, 3, 4, 5] for m in found)
    late = np.array([m.edges["frequency"][:2] for m in found if m.t_us > 250_000])
    assert np.all(np.abs(late / 200.0 - 1) < 0.02)
    amp = np.array([m.edges["amplitude"][:2] for m in found if m.t_us > 250_000]).mean(axis=0)
    assert amp == pytest.approx([1.0, 0.9], rel=0.08)  # the simulator's amplitudes (rad)
    seqs = [m.seq for m in receiver.messages]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # nothing lost on loopback, seq per datagram
    st = [m for m in receiver.messages if isinstance(m, EdgeStatus)][-1]
    assert st.frames_seen > 100_000 and st.last_error == ""


def test_no_fly_sends_empty_estimates_and_says_why(edge_any: Path, receiver, tmp_path: Path,
                                                    no_sanitizer_report) -> None:
    rng = np.random.default_rng(5)
    ev = np.zeros(40_000, EVENT_DTYPE)  # 0.4 s of uniform noise
    ev["t"] = np.sort(rng.integers(0, 400_000, len(ev)))
    ev["x"], ev["y"] = rng.integers(0, 128, len(ev)), rng.integers(0, 128, len(ev))
    path = tmp_path / "noise.aedat4"
    write_events(path, ev, width=128, height=128)
    rc, err = run(edge_any, receiver, path, "--wingbeat", "1", "--realtime", "0")
    no_sanitizer_report(err)
    assert rc == 0, err
    assert "no fly in the initialisation window" in err and "no beating wing in view" in err
    wb = [m for m in receiver.messages if isinstance(m, DvsWingbeat)]
    assert len(wb) > 70 and all(m.n_edges == 0 for m in wb)
    st = [m for m in receiver.messages if isinstance(m, EdgeStatus)][-1]
    assert st.last_error_code == 42 and "no beating wing in view" in st.last_error


@pytest.mark.parametrize("opt", [("--wingbeat-harmonics", "5"), ("--wingbeat-start-freq", "-3"),
                                 ("--wingbeat-report-us", "10"), ("--wingbeat", "maybe")])
def test_bad_wingbeat_options_are_refused(edge_bin: Path, opt: tuple[str, str]) -> None:
    p = subprocess.run([str(edge_bin), "--source", "events", "--input", "x.aedat4", *opt], capture_output=True,
                       text=True, timeout=30)
    assert p.returncode == 2 and f"option {opt[0][2:]} = \"{opt[1]}\"" in p.stderr
