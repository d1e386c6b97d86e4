import numpy as np
import pytest

from flytrack_host.sim.flight import Arena, FlightParams, simulate_flight


def test_animals_stay_inside_and_fly_at_paper_speed():
    gt = simulate_flight(4, 10.0, 100.0, seed=3)
    assert gt.pos.shape == (1000, 4, 3)
    assert np.all(gt.arena.contains(gt.pos.reshape(-1, 3)))
    hs = gt.horizontal_speed()[~gt.landed]
    # Seed 000 section 7: mean 0.15 m/s, sd 0.07 m/s. Our model aims at that, loosely.
    assert 0.10 < hs.mean() < 0.20
    assert 0.03 < hs.std() < 0.10
    assert gt.meta["saccades"] + gt.meta["wall_saccades"] > 10
    norms = np.linalg.norm(gt.axis, axis=-1)
    assert np.allclose(norms, 1.0, atol=1e-6)


def test_saccades_are_fast_turns():
    gt = simulate_flight(1, 10.0, 200.0, seed=5)
    v = gt.vel[:, 0, :2]
    ok = ~gt.landed[1:, 0] & ~gt.landed[:-1, 0]
    ang = np.arctan2(v[:, 1], v[:, 0])
    rate = np.abs((np.diff(ang) + np.pi) % (2 * np.pi) - np.pi) * gt.fps
    rate = rate[ok]
    # Mostly straight (median well under 1 rad/s, ignoring the wobble) with bursts above 10 rad/s.
    assert np.median(rate) < 3.0
    assert np.max(rate) > 10.0


def test_landings_rest_on_a_surface_and_take_off():
    p = FlightParams(land_rate_hz=0.5, min_flight_s=0.5)
    gt = simulate_flight(2, 20.0, 100.0, seed=1, params=p)
    assert gt.meta["landings"] >= 1 and gt.meta["takeoffs"] >= 1
    landed = gt.landed
    assert np.all(np.linalg.norm(gt.vel[landed], axis=-1) == 0)
    # A landed animal sits within a millimetre of the floor or a long wall.
    pos = gt.pos[landed]
    a = gt.arena
    d = np.minimum.reduce([pos[:, 2] - a.lo[2], pos[:, 1] - a.lo[1], a.hi[1] - pos[:, 1]])
    assert np.all(d < 1e-3)


def test_close_encounters_happen_and_are_flagged():
    gt = simulate_flight(3, 12.0, 50.0, seed=2, params=FlightParams(encounter_rate_hz=0.8))
    assert gt.meta["encounters"] > 0
    close = gt.close_frames(0.03)
    assert close.any()
    assert gt.pair_distances().min() < 0.03


def test_deterministic_by_seed():
    a = simulate_flight(2, 2.0, 100.0, seed=9)
    b = simulate_flight(2, 2.0, 100.0, seed=9)
    c = simulate_flight(2, 2.0, 100.0, seed=10)
    assert np.array_equal(a.pos, b.pos)
    assert not np.array_equal(a.pos, c.pos)


@pytest.mark.parametrize(
    "kw, msg",
    [
        ({"n_animals": 0}, "animals"),
        ({"fps": 0.0}, "fps"),
        ({"seconds": -1.0}, "seconds"),
        ({"seconds": float("nan")}, "seconds"),
    ],
)
def test_bad_arguments_are_clear_errors(kw, msg):
    args = {"n_animals": 2, "seconds": 1.0, "fps": 100.0} | kw
    with pytest.raises(ValueError, match=msg):
        simulate_flight(**args)


def test_bad_arena_is_an_error():
    with pytest.raises(ValueError, match="arena length"):
        Arena(length=0.0)


@pytest.mark.parametrize("n", [2, 3])
def test_a_ten_second_run_has_a_landing_and_a_close_pass(n):
    # The README: a run of 10 s (the demo's length) has at least one landing and one pass closer than
    # 3 cm, whatever the seed (the scripted landing at a quarter and meeting at half of the run).
    for seed in range(5):
        gt = simulate_flight(n, 10.0, 100.0, seed=seed)
        assert gt.landed.any() and gt.meta["takeoffs"] >= 1, seed
        assert gt.pair_distances().min() < 0.03, seed
