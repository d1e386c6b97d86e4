"""The simulated DVS: events where the animals move, none elsewhere beyond the noise rate, refractory
period kept, and an EVT 2.0 stream the project's own event reader decodes event for event."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.sim.dvs import DvsParams, DvsRenderer, Evt2Encoder, evt2_header, make_dvs_cameras
from flytrack_host.sim.flight import Arena, simulate_flight


@pytest.fixture(scope="module")
def world():
    arena = Arena()
    gt = simulate_flight(2, 0.5, 100.0, seed=3, arena=arena)
    cam = make_dvs_cameras(1, arena, seed=3, sensor="davis346")[0]
    return gt, cam


def _run(gt, cam, params):
    r = DvsRenderer(cam, params, seed=1)
    chunks = [r.period(gt.t[k], gt.pos[k], gt.body_length_m, gt.body_width_m) for k in range(gt.n_frames)]
    return r, chunks


def test_events_follow_the_animals_and_noise_keeps_its_rate(world):
    gt, cam = world
    assert (cam.width, cam.height) == (346, 260)
    r, chunks = _run(gt, cam, DvsParams(noise_hz_per_px=0.0))
    ev = np.concatenate(chunks)
    assert len(ev) > 200, len(ev)  # two flying animals leave trails of events
    assert np.all(np.diff(np.concatenate([c["t"] for c in chunks])) >= 0)  # time-ordered across periods
    # Every event lies near where an animal was (within a few blob radii of its projected path).
    uv = cam.project(gt.pos.reshape(-1, 3))
    d = np.min(np.hypot(ev["x"][:, None] - uv[None, :, 0], ev["y"][:, None] - uv[None, :, 1]), axis=1)
    assert np.percentile(d, 99) < 6.0, np.percentile(d, 99)
    assert set(np.unique(ev["p"])) == {0, 1}  # a dark animal: OFF where it arrives, ON where it leaves
    # Refractory period: no pixel fires twice within it.
    key = ev["y"].astype(np.int64) * cam.width + ev["x"]
    order = np.lexsort((ev["t"], key))
    same = key[order][1:] == key[order][:-1]
    assert np.all(np.diff(ev["t"][order])[same] >= 500)
    # Noise alone: the set rate per pixel, anywhere on the sensor.
    rate = 2.0
    rn, chunks_n = _run(gt, cam, DvsParams(noise_hz_per_px=rate))
    n_noise = sum(len(c) for c in chunks_n) - len(ev)
    expect = rate * cam.width * cam.height * (gt.t[-1] - gt.t[0])
    assert abs(n_noise - expect) < 5 * np.sqrt(expect) + 0.05 * expect, (n_noise, expect)


def test_evt2_stream_decodes_event_for_event_with_its_syncs(world, tmp_path):
    from flytrack_host.dvs.events.files import EventReader

    gt, cam = world
    r = DvsRenderer(cam, DvsParams(noise_hz_per_px=0.5), seed=2, t0_us=5_000_000)
    enc = Evt2Encoder()
    data = [evt2_header(cam.width, cam.height)]
    sent = []
    for k in range(gt.n_frames):
        ev = r.period(gt.t[k], gt.pos[k], gt.body_length_m, gt.body_width_m)
        sent.append(ev)
        data.append(enc.encode(ev, sync_us=r.to_us(gt.t[k])))
    path = tmp_path / "sim.raw"
    path.write_bytes(b"".join(data))
    sent_a = np.concatenate(sent)
    with EventReader(path, "evt2") as rd:
        got = np.concatenate(list(rd))
        info = rd.info
    assert (info.width, info.height) == (cam.width, cam.height)
    assert len(got) == len(sent_a)
    assert np.array_equal(got["t"], sent_a["t"]) and np.array_equal(got["x"], sent_a["x"])
    assert np.array_equal(got["y"], sent_a["y"]) and np.array_equal(got["p"].astype(int), sent_a["p"].astype(int))
    assert info.n_triggers == gt.n_frames  # one sync event per trigger pulse


def test_encoder_refuses_time_going_back():
    enc = Evt2Encoder()
    ev = np.zeros(2, dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    ev["t"] = [100, 50]
    with pytest.raises(ValueError, match="non-decreasing"):
        enc.encode(ev)
    with pytest.raises(ValueError, match="contrast threshold"):
        DvsParams(contrast_threshold=0.0)
