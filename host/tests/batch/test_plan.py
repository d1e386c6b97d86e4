"""Batch planning: parameter sets from --set/--sweep, one task per recording and set, clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from flytrack_host.batch.plan import BatchError, ParamSet, param_sets, plan_exports, plan_retracks


def test_sweeps_make_every_combination_with_the_fixed_sets():
    sets = param_sets(["confirm_min_frames=3"], ["motion_noise_scale=0.05,0.1", "birth_max_reproj_px=3,5,8"])
    assert len(sets) == 6
    assert sets[0].sets == ("confirm_min_frames=3", "motion_noise_scale=0.05", "birth_max_reproj_px=3")
    assert sets[-1].overrides == {"confirm_min_frames": "3", "motion_noise_scale": "0.1", "birth_max_reproj_px": "8"}
    assert len({s.name for s in sets}) == 6
    assert param_sets() == [ParamSet()] and ParamSet().name == "base"


@pytest.mark.parametrize(("sets", "sweeps", "msg"), [
    (["motion_noise_scale"], [], "--set 'motion_noise_scale': write KEY=VALUE"),
    ([], ["motion_noise_scale=0.1,,0.2"], "an empty value"),
    ([], ["motion_noise_scale=0.1,0.1"], "repeated"),
    (["motion_noise_scale=0.1"], ["motion_noise_scale=0.2,0.3"], "motion_noise_scale is given more than once"),
])
def test_bad_options_are_named(sets, sweeps, msg):
    with pytest.raises(BatchError, match=msg):
        param_sets(sets, sweeps)


def test_outputs_are_fixed_per_recording_and_set(tmp_path: Path):
    a = tmp_path / "x" / "day1.flytrack"
    b = tmp_path / "y" / "day1.flytrack"
    c = tmp_path / "day2.braidz"
    for p in (a, b):
        p.mkdir(parents=True)
    c.write_bytes(b"PK")
    tasks = plan_retracks([a, c], param_sets([], ["motion_noise_scale=0.1,0.2"]), tmp_path / "out")
    assert [t.out.relative_to(tmp_path / "out").as_posix() for t in tasks] == [
        "day1/motion_noise_scale-0.1.flytrack", "day1/motion_noise_scale-0.2.flytrack",
        "day2/motion_noise_scale-0.1.flytrack", "day2/motion_noise_scale-0.2.flytrack"]
    assert len({t.key for t in tasks}) == 4
    # Same name in two folders: kept apart by the parent folder's name.
    tasks = plan_retracks([a, b], [ParamSet()], tmp_path / "out")
    assert [t.out.parent.name for t in tasks] == ["x-day1", "y-day1"]
    with pytest.raises(BatchError, match="no such recording: .*nope"):
        plan_retracks([tmp_path / "nope"], [ParamSet()], tmp_path / "out")
    with pytest.raises(BatchError, match="export formats are braidz and csv"):
        plan_exports([a], tmp_path / "out", ())
