"""The synchroniser's sliding windows keep the minimum and maximum of their tuples' second values
as tuples come and go; they must always equal min()/max() over what the window holds."""

import copy
import random

from flytrack_host.sync import _Window


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
