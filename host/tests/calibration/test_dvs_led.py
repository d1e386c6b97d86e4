"""DVS cameras calibrated with the frame cameras from a blinking LED (issue 13): the LED found in the
events by its frequency, stamped with trigger frames through the sync events, then self-calibrated
with the frame cameras. Ground truth from sim/dvs_wand.py (a distractor that does not blink, noise,
the LED turned away from a camera at times, a DVS clock 40 ppm fast with its own epoch)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from flytrack_host.calibration.dvs_cli import extract_file, to_observations
from flytrack_host.calibration.evaluate import errors_against_truth
from flytrack_host.calibration.led_events import (
    LedParams,
    dominant_frequencies,
    led_points,
    periodic_mask,
    sync_frames,
)
from flytrack_host.calibration.observations import load_points, save_points
from flytrack_host.calibration.selfcal import self_calibrate
from flytrack_host.cli import app
from flytrack_host.dvs.events import EVENT_DTYPE, read_events_and_triggers, write_events
from flytrack_host.sim.dvs_wand import simulate_wand

LED_HZ = 500.0


def _blink(x: int, y: int, hz: float, n: int, t0: int, rng: np.random.Generator, burst: int = 2) -> list[tuple]:
    """A pixel switched on and off at hz (50 % duty), each switch a burst of events 300 us apart."""
    T = 1e6 / hz
    out = []
    for k in range(n):
        for pol, at in ((1, 0.0), (0, 0.5)):
            t = t0 + k * T + at * T + rng.uniform(0, 60)
            out += [(int(t + 300 * b), x, y, pol) for b in range(burst)]
    return out


def _events(rows: list[tuple]) -> np.ndarray:
    ev = np.zeros(len(rows), EVENT_DTYPE)
    a = np.array(rows, dtype=np.int64).reshape(-1, 4)
    ev["t"], ev["x"], ev["y"], ev["p"] = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    return ev[np.argsort(ev["t"], kind="stable")]


def test_periodic_mask_keeps_the_led_frequency_only():
    rng = np.random.default_rng(1)
    rows = _blink(10, 10, 500, 30, 1000, rng) + _blink(20, 20, 300, 18, 1000, rng)
    rows += [(5000, 30, 30, 0), (9000, 30, 30, 1)]  # an edge passing: OFF then ON, once
    n_noise = 3000
    rows += list(zip(rng.integers(0, 60_000, n_noise).tolist(), rng.integers(0, 64, n_noise).tolist(),
                     rng.integers(0, 64, n_noise).tolist(), rng.integers(0, 2, n_noise).tolist(), strict=True))
    ev = _events(rows)
    m = periodic_mask(ev, 64, LedParams(LED_HZ))
    at = lambda x, y: (ev["x"] == x) & (ev["y"] == y)  # noqa: E731
    assert m[at(10, 10)].mean() > 0.95  # the LED pixel (noise landing on it may break a cycle)
    assert not m[at(20, 20)].any() and not m[at(30, 30)].any()
    noise = ~at(10, 10) & ~at(20, 20) & ~at(30, 30)
    assert m[noise].mean() < 0.01
    # The frequencies the events repeat at, strongest first.
    f = dominant_frequencies(ev, 64, top=2)
    assert {round(f[0][0], -1), round(f[1][0], -1)} == {500, 300}, f
    # Off, every event counts.
    assert periodic_mask(ev, 64, LedParams(LED_HZ, check_frequency=False)).all()


def test_sync_frames_skip_a_missed_pulse():
    t = np.array([0, 10_000, 20_001, 40_000, 50_000], np.int64)
    frames, missed = sync_frames(t, first_frame=7)
    assert frames.tolist() == [7, 8, 9, 11, 12] and missed == 1


@pytest.fixture(scope="module")
def wand(tmp_path_factory):
    out = tmp_path_factory.mktemp("wand")
    return simulate_wand(out, n_frame_cameras=4, n_dvs=2, seconds=6.0, seed=0)


@pytest.fixture(scope="module")
def extracted(wand):
    return {n: extract_file(p, n, LedParams(LED_HZ)) for n, p in wand.dvs_files.items()}


def _point_errors(wand, name, pts):
    cam = wand.dvs_cameras[name]
    return np.linalg.norm(pts.uv - cam.project(wand.led[pts.frame]), axis=1)


def test_points_are_the_led_at_its_trigger_frame(wand, extracted):
    for name, res in extracted.items():
        pts = res.points
        e = _point_errors(wand, name, pts)
        cam = wand.dvs_cameras[name]
        seen = cam.in_view(wand.led, margin=2.0) & ~wand.dvs_hidden[name]
        # Frame by frame against the LED's true position projected at that frame.
        assert np.median(e) < 0.15, (name, np.median(e))
        assert np.percentile(e, 95) < 0.7, (name, np.percentile(e, 95))
        assert np.mean(e < 1.0) > 0.98, (name, np.sort(e)[-10:])
        assert len(pts.frame) >= 0.95 * seen.sum(), (name, len(pts.frame), seen.sum())
        # Where the LED was turned away from this camera there is (almost) no point.
        assert wand.dvs_hidden[name][pts.frame].mean() < 0.02
        assert pts.stats["missed_syncs"] == 0 and pts.stats["syncs"] == len(wand.t)
    # The whole file at once gives exactly what the chunked reader gave.
    name = "dvs1"
    ev, trig = read_events_and_triggers(wand.dvs_files[name])
    whole = led_points(ev, trig["t"], 346, 260, LedParams(LED_HZ))
    np.testing.assert_array_equal(whole.frame, extracted[name].points.frame)
    np.testing.assert_allclose(whole.uv, extracted[name].points.uv, atol=1e-9)


def test_without_the_frequency_check_the_distractor_corrupts_the_points(wand):
    name = "dvs1"
    res = extract_file(wand.dvs_files[name], name, LedParams(LED_HZ, check_frequency=False))
    e = _point_errors(wand, name, res.points)
    assert np.mean(e > 5.0) > 0.05, np.mean(e > 5.0)  # points on the ball while the LED is turned away


def test_selfcal_frame_and_dvs_cameras_together(wand, extracted):
    obs = to_observations(list(extracted.values()), wand.frame_obs)
    assert obs.camera_names == ["cam1", "cam2", "cam3", "cam4", "dvs1", "dvs2"]
    res = self_calibrate(obs, seed=0)
    truth = {**wand.frame_cameras, **wand.dvs_cameras}
    te = errors_against_truth(res.cameras, res.points, truth, wand.led[res.point_frames])
    for ci, name in enumerate(obs.camera_names):
        if not name.startswith("dvs"):
            continue
        use = res.inlier & (obs.cam == ci)
        rep = float(np.mean(np.linalg.norm(res.residuals[use], axis=1)))
        print(f"{name}: reprojection {rep:.3f} px, against the true camera {te[name]['proj_mean_px']:.3f} px, "
              f"centre {1000 * te[name]['centre']:.1f} mm")
        assert use.sum() >= 0.95 * (obs.cam == ci).sum()
        assert rep < 0.25, (name, rep)
        assert te[name]["proj_mean_px"] < 0.2, (name, te[name])
        assert te[name]["centre"] < 0.025, (name, te[name])


def _cli(*args: str):
    return CliRunner().invoke(app, ["calibrate", *args])


def _text(r) -> str:
    return " ".join(r.output.split())


def test_cli_dvs_points_and_its_errors(wand, extracted, tmp_path: Path):
    frames = tmp_path / "frames.csv"
    save_points(wand.frame_obs, frames)
    out = tmp_path / "points.csv"
    r = _cli("dvs-points", str(wand.dvs_files["dvs1"]), "--led-hz", "500", "--with", str(frames), "-o", str(out))
    assert r.exit_code == 0, r.output
    assert "M events/s" in _text(r) and "per CPU second" in _text(r)
    obs = load_points(out)
    assert obs.camera_names[-1] == "dvs1" and obs.sizes[-1] == (346, 260)
    mine = obs.cam == obs.camera_names.index("dvs1")
    np.testing.assert_array_equal(obs.frame[mine], extracted["dvs1"].points.frame)
    # Pulse times given as a CSV (frame numbers from elsewhere) instead of the file's sync events.
    ev, trig = read_events_and_triggers(wand.dvs_files["dvs1"])
    sync = tmp_path / "sync.csv"
    sync.write_text("frame,t_us\n" + "".join(f"{100 + i},{t}\n" for i, t in enumerate(trig["t"])))
    out2 = tmp_path / "p2.csv"
    r = _cli("dvs-points", str(wand.dvs_files["dvs1"]), "--led-hz", "500", "--sync", str(sync), "-o", str(out2))
    assert r.exit_code == 0, r.output
    np.testing.assert_array_equal(load_points(out2).frame, extracted["dvs1"].points.frame + 100)
    r = _cli("dvs-points", str(wand.dvs_files["dvs1"]), "--led-hz", "500", "--first-frame", "100", "-o", str(out2))
    assert r.exit_code == 0, r.output
    np.testing.assert_array_equal(load_points(out2).frame, extracted["dvs1"].points.frame + 100)
    # Wrong frequency: no LED, and the message says what the events do repeat at.
    r = _cli("dvs-points", str(wand.dvs_files["dvs2"]), "--led-hz", "700", "-o", str(tmp_path / "x.csv"))
    assert r.exit_code == 2 and "no LED blinking at 700 Hz" in _text(r) and "500 Hz" in _text(r), _text(r)
    assert not (tmp_path / "x.csv").exists()
    # A damaged (cut) file: the events before the damage are used, with a warning.
    cut = tmp_path / "cut.raw"
    cut.write_bytes(wand.dvs_files["dvs1"].read_bytes()[:1_000_002])
    r = _cli("dvs-points", str(cut), "--led-hz", "500", "-o", str(tmp_path / "cut.csv"))
    assert r.exit_code == 0 and "truncated" in _text(r) and "events before the damage were used" in _text(r)
    n_cut = len(load_points(tmp_path / "cut.csv").frame)
    assert 0 < n_cut < len(extracted["dvs1"].points.frame)
    # A file without sync events.
    nosync = tmp_path / "nosync.aedat4"
    write_events(nosync, ev[:50_000], 346, 260)
    r = _cli("dvs-points", str(nosync), "--led-hz", "500", "-o", str(tmp_path / "y.csv"))
    assert r.exit_code == 2 and "no sync" in _text(r), _text(r)
    # Event times that go back (a timestamp reset): AEDAT 2.0 written byte by byte.
    import struct

    recs = [(0x8000, 500), ((5 << 8), 1000), ((6 << 8), 2000), ((7 << 8), 1500), (0x8000, 2500)]
    back = tmp_path / "reset.aedat"
    back.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: DVS128\r\n" + b"".join(struct.pack(">II", a, t) for a, t in recs))
    r = _cli("dvs-points", str(back), "--led-hz", "500", "-o", str(tmp_path / "v.csv"))
    assert r.exit_code == 2 and "event times go back (to 1500 us after 2000 us)" in _text(r), _text(r)
    # Not an event file, and no file.
    r = _cli("dvs-points", str(frames), "--led-hz", "500", "-o", str(tmp_path / "z.csv"))
    assert r.exit_code == 2 and "not an event file" in _text(r), _text(r)
    r = _cli("dvs-points", str(tmp_path / "missing.raw"), "--led-hz", "500", "-o", str(tmp_path / "z.csv"))
    assert r.exit_code == 2 and "no such file" in _text(r)
    # A camera name already in the frame cameras' file.
    r = _cli("dvs-points", str(wand.dvs_files["dvs1"]), "--camera", "cam1", "--led-hz", "500", "--with",
             str(frames), "-o", str(tmp_path / "w.csv"))
    assert r.exit_code == 2 and "already in the points file" in _text(r)


def test_cli_dvs_sim_writes_what_the_readme_uses(tmp_path: Path):
    from flytrack_host.geometry.formats import load_calibration

    out = tmp_path / "wand"
    r = _cli("dvs-sim", str(out), "--seconds", "0.3", "--dvs", "1", "--frame-cameras", "3")
    assert r.exit_code == 0, r.output
    cams = load_calibration(out / "truth.xml")
    assert sorted(cams) == ["cam1", "cam2", "cam3", "dvs1"] and (cams["dvs1"].width, cams["dvs1"].height) == (346, 260)
    obs = load_points(out / "frames.csv")
    assert obs.camera_names == ["cam1", "cam2", "cam3"] and obs.frame.max() <= 29
    led = np.loadtxt(out / "led.csv", delimiter=",", skiprows=1)
    assert led.shape == (30, 4)
    ev, trig = read_events_and_triggers(out / "dvs1.raw")
    assert len(trig) == 30 and len(ev) > 1000
    r = _cli("dvs-sim", str(out), "--seconds", "0.01")
    assert r.exit_code == 2 and "fewer than 10 frames" in _text(r)
