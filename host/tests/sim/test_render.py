import numpy as np
import pytest

from flytrack_host.sim.flight import Arena
from flytrack_host.sim.render import CameraRenderer, RenderParams
from flytrack_host.sim.rig import make_cameras


@pytest.fixture(scope="module")
def cam():
    return make_cameras(1, Arena(), seed=2)[0]


def _centroid(diff):
    ys, xs = np.nonzero(diff > 20)
    w = diff[ys, xs].astype(float)
    return np.array([np.sum(xs * w) / w.sum(), np.sum(ys * w) / w.sum()])


def test_dark_blob_is_where_the_animal_projects(cam):
    p = RenderParams(noise_sigma=0.0, false_blob_rate=0.0, drift_amplitude=0.0)
    r = CameraRenderer(cam, p, seed=0)
    X = np.array([[0.1, 0.02, 0.15]])
    ax = np.array([[1.0, 0.0, 0.0]])
    empty = r.render(0.0, np.zeros((0, 3)), np.zeros((0, 3)), 0.0025, 0.001).copy()
    drawn = []
    img = r.render(0.0, X, ax, 0.0025, 0.001, drawn).copy()
    diff = empty.astype(int) - img.astype(int)
    assert diff.max() > 50  # a dark blob well above the edge's default threshold (30)
    uv = cam.project(X)[0]
    assert np.linalg.norm(_centroid(diff) - uv) < 0.25
    assert drawn[0].animal == 0


def test_bright_animals_and_outside_view(cam):
    p = RenderParams(noise_sigma=0.0, false_blob_rate=0.0, drift_amplitude=0.0, bright_fraction=1.0)
    r = CameraRenderer(cam, p, seed=0)
    empty = r.render(0.0, np.zeros((0, 3)), np.zeros((0, 3)), 0.0025, 0.001).copy()
    img = r.render(0.0, np.array([[0.0, 0.0, 0.1]]), np.array([[0.0, 1.0, 0.0]]), 0.0025, 0.001).copy()
    assert (img.astype(int) - empty).max() > 40
    far = np.array([[50.0, 50.0, 0.1]])  # outside the view: nothing drawn
    drawn = []
    img2 = r.render(0.0, far, np.array([[1.0, 0, 0]]), 0.0025, 0.001, drawn)
    assert drawn == [] and np.array_equal(img2, empty)


def test_nearer_animal_hides_one_behind_it(cam):
    p = RenderParams(noise_sigma=0.0, false_blob_rate=0.0, drift_amplitude=0.0)
    r = CameraRenderer(cam, p, seed=0)
    near = np.array([0.0, 0.0, 0.15])
    behind = near + (near - cam.center) / np.linalg.norm(near - cam.center) * 0.05
    drawn = []
    r.render(0.0, np.array([behind, near]), np.array([[1.0, 0, 0]] * 2), 0.0025, 0.001, drawn)
    assert [d.animal for d in drawn] == [1]


def test_noise_level_and_vignetting(cam):
    p = RenderParams(noise_sigma=3.0, false_blob_rate=0.0, drift_amplitude=0.0)
    r = CameraRenderer(cam, p, seed=0)
    a = r.render(0.0, np.zeros((0, 3)), np.zeros((0, 3)), 0.0025, 0.001).astype(float)
    b = r.render(0.01, np.zeros((0, 3)), np.zeros((0, 3)), 0.0025, 0.001).astype(float)
    sd = np.std(a - b) / np.sqrt(2)
    assert 2.5 < sd < 3.5
    h, w = a.shape
    assert a[h // 2 - 10 : h // 2 + 10, w // 2 - 10 : w // 2 + 10].mean() > a[:20, :20].mean() + 10


def test_false_blobs_appear_at_their_rate(cam):
    p = RenderParams(noise_sigma=1.0, false_blob_rate=0.5, false_blob_frames=(1, 1))
    r = CameraRenderer(cam, p, seed=0)
    n = 0
    for k in range(200):
        drawn = []
        r.render(k / 100, np.zeros((0, 3)), np.zeros((0, 3)), 0.0025, 0.001, drawn)
        n += len(drawn)
    assert 60 < n < 140


def test_bad_render_params():
    with pytest.raises(ValueError, match="noise"):
        RenderParams(noise_sigma=-1.0)
    with pytest.raises(ValueError, match="contrast"):
        RenderParams(contrast=0.0)
