"""The synchroniser's sliding windows keep the minimum and maximum of their tuples' second values
as tuples come and go; they must always equal min()/max() over what the window holds."""

import copy
import random

from flytrack_host.intake.sync import _Window


def test_window_min_max_follow_appends_pops_and_clears():
    rng = random.Random(5)
    w = _Window()
    ref: list[tuple] = []
    for step in range(20_000):
        r = rng.random()
        if r < 0.55 or not ref:
            item = (step, float(rng.choice([rng.gauss(0, 1), 0.5, -0.5, 0.0])), step * 0.01)  # ties too
            w.append(item)
            ref.append(item)
        elif r < 0.999:
            assert w.popleft() is ref.pop(0)
        else:
            w.clear()
            ref.clear()
        assert list(w) == ref
        if ref:
            assert w.min1() == min(x[1] for x in ref)
            assert w.max1() == max(x[1] for x in ref)


def test_window_copy_and_construction_keep_the_extremes():
    w = _Window([(0, 3.0), (1, -1.0), (2, 2.0)])
    assert (w.min1(), w.max1()) == (-1.0, 3.0)
    c = copy.copy(w)
    assert list(c) == list(w) and (c.min1(), c.max1()) == (-1.0, 3.0)
    w.popleft()
    w.popleft()
    assert (w.min1(), w.max1()) == (2.0, 2.0)


def test_lag_window_min_lag_equals_the_python_formula_bit_for_bit():
    """The mapped-ahead check reads every camera's lags under the clock model of now through
    `_LagWindow.min_lag`: it must give exactly what walking the tuples gives, through ring wrap-around,
    growth past its first capacity, pops and clears, with and without the arrival cut-off."""
    from flytrack_host.intake.sync import _LagWindow

    rng = random.Random(11)
    w = _LagWindow()
    ref_items: list[tuple] = []
    t = 1000.0
    tf = 0
    for step in range(6000):
        r = rng.random()
        if r < 0.6 or not ref_items:
            t += rng.uniform(0.0005, 0.02)
            tf += rng.choice([1, 1, 1, 2])
            item = (t, rng.gauss(0.001, 0.0003), tf)
            w.append(item)
            ref_items.append(item)
        elif r < 0.998:
            assert w.popleft() is ref_items.pop(0)
        else:
            w.clear()
            ref_items.clear()
        if step % 7 == 0:
            t_ref, ref, slope = t - rng.uniform(0, 0.01), max(tf - rng.randrange(5), 0), 0.01 * (1 + rng.gauss(0, 4e-5))
            since = t - rng.uniform(0.0, 1.5)

            def lag(x: tuple, t_ref: float = t_ref, ref: int = ref, slope: float = slope) -> float:
                return x[0] - (t_ref + (x[2] - ref) * slope)

            want_all = min((lag(x) for x in ref_items), default=float("inf"))
            want_since = min((lag(x) for x in ref_items if x[0] >= since), default=float("inf"))
            assert w.min_lag(t_ref, ref, slope) == want_all
            assert w.min_lag(t_ref, ref, slope, since=since) == want_since
        if ref_items and step % 500 == 0:
            assert len(w._t) >= len(ref_items)
    assert len(w._t) > 128  # it grew at least once
