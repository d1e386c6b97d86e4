import numpy as np
import pytest

from flytrack_host.rig import load_rig
from flytrack_host.sim.flight import Arena
from flytrack_host.sim.rig import make_cameras, rig_config, to_toml, write_rig


def test_every_camera_sees_the_whole_arena_with_real_distortion():
    arena = Arena()
    cams = make_cameras(5, arena, seed=1)
    assert len({c.name for c in cams}) == 5
    for c in cams:
        assert np.all(c.in_view(arena.corners()))
        assert c.dist[0] < 0  # barrel distortion, as with short lenses
        assert 600 < c.K[0, 0] < 950
        # The calibration round-trips: undistort(distort(p)) == p.
        uv = c.project(arena.corners())
        assert np.allclose(c.distort(c.undistort(uv)), uv, atol=1e-6)
    centers = np.array([c.center for c in cams])
    assert np.min(np.linalg.norm(centers[:, None] - centers[None], axis=-1) + np.eye(5) * 9) > 0.3


def test_camera_count_is_checked():
    with pytest.raises(ValueError, match="cameras"):
        make_cameras(0, Arena())


def test_rig_file_round_trips_through_load_rig(tmp_path):
    cams = make_cameras(3, Arena(), seed=0)
    rig = rig_config(cams, 100.0, "127.0.0.1:7500", "software", "/dev/pts/9", None, "rec",
                     live_subscribers=["127.0.0.1:7600"])
    path = write_rig(rig, tmp_path / "rig.toml")
    back = load_rig(path)
    assert [c.name for c in back.cameras] == ["cam1", "cam2", "cam3"]
    assert back.trigger.kind == "software" and back.trigger.fps == 100.0
    assert back.host.listen == "127.0.0.1:7500"
    assert back.host.live_subscribers == ["127.0.0.1:7600"]
    assert back.model_dump(exclude={"base_dir"}) == rig.model_dump(exclude={"base_dir"})


def test_toml_writer_escapes_and_refuses_nan():
    assert 'name = "a\\"b"' in to_toml({"name": 'a"b'})
    with pytest.raises(ValueError):
        to_toml({"x": float("nan")})
