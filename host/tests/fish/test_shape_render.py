"""Shape maps (eqs 3.1-3.7), the renderer and the background subtraction (eq. 5.1) on known shapes."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.fish.render import background, coverage, dense_model, render_image
from flytrack_host.fish.shape import (
    arclength,
    body_axes,
    default_model,
    heading_from_angles,
    make_state,
    midline_world,
    p_for_length,
    section_frames,
)
from flytrack_host.fish.silhouette import warm_up
from flytrack_host.fish.views import AirView
from flytrack_host.geometry.camera import Camera


def test_body_frame_has_no_roll_and_is_orthonormal() -> None:
    h = heading_from_angles(np.array([0.3, 2.0, -1.0]), np.array([0.2, -0.4, 0.0]))
    R = body_axes(h)
    for Rb in R:
        assert np.allclose(Rb.T @ Rb, np.eye(3), atol=1e-12)
        assert abs(Rb[2, 1]) < 1e-12  # pitch axis g x h is horizontal: no roll
        assert np.linalg.det(Rb) == pytest.approx(1.0)


def test_straight_midline_maps_to_a_line_behind_the_head() -> None:
    X = make_state([0.1, 0.2, 0.3], heading_from_angles(0.5, 0.1), [0.05, 0, 0, 0, 0])
    s = np.linspace(0, 1, 11)
    m, t = midline_world(X, s)
    h = X[0, 3:6]
    assert np.allclose(m[0, 0], X[0, :3])
    assert np.allclose(m[0, -1], X[0, :3] - 0.05 * h)  # tail one length behind the head centre
    assert np.allclose(t[0], -h)
    assert arclength(X[:, 6:])[0] == pytest.approx(0.05)


def test_bent_midline_keeps_its_length_and_bends_sideways() -> None:
    p = p_for_length(np.array([[0.5, 0.0, -0.1], [0.5, -0.95, 0.3]]), 0.05)
    assert np.allclose(arclength(p), 0.05, atol=1e-7)
    assert np.all(p[:, 0] < 0.05)  # the bend shortens the extent along the heading
    X = make_state(np.zeros((2, 3)), np.tile([1.0, 0, 0], (2, 1)), p)
    m, _ = midline_world(X, np.linspace(0, 1, 5))
    assert np.allclose(m[..., 2], 0.0)  # f3 = 0: lateral bending in the horizontal body plane
    assert m[0, -1, 1] > 0.005  # the tail swings to +y (g x h) for p3 > 0


def test_cross_sections_are_normal_to_the_midline_with_the_model_sizes() -> None:
    model = default_model(0.05)
    X = make_state([0.0, 0.0, 0.2], heading_from_angles(1.0, 0.2), p_for_length(np.array([[0.3, 0.1, 0.0]]), 0.05))
    S = model.surface(X, u=np.array([0.0, np.pi / 2, np.pi, 3 * np.pi / 2]))[0]
    m, t = midline_world(X, model.s)
    x, y = section_frames(t)
    for i in range(len(model.s)):
        assert np.allclose((S[i] - m[0, i]) @ t[0, i], 0.0, atol=1e-12)  # in the plane normal to t(s)
        assert np.linalg.norm(S[i, 0] - S[i, 2]) / 2 == pytest.approx(model.a[i])
        assert np.linalg.norm(S[i, 1] - S[i, 3]) / 2 == pytest.approx(model.b[i])
        centre = (S[i, 1] + S[i, 3]) / 2
        assert (centre - m[0, i]) @ y[0, i] == pytest.approx(model.d[i])
        assert abs(x[0, i, 2]) < 1e-12  # the ellipse's a-axis is horizontal


def _top_camera(size: int = 320) -> AirView:
    return AirView(Camera.look_at("top", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), size, size, focal_px=2000.0,
                                  up=(0.0, 1.0, 0.0)))


def test_rendered_area_matches_the_projected_outline() -> None:
    view = _top_camera()
    model = dense_model(default_model(0.05))
    X = make_state([0.025, 0.0, 0.0], [1.0, 0.0, 0.0], [0.05, 0, 0, 0, 0])
    cov = coverage(view, model, X)
    scale = 2000.0 / 1.0  # px per metre at 1 m
    s = model.s
    area = np.trapezoid(2 * model.a, s * 0.05) * scale**2  # outline of a straight fish seen from above
    assert cov.sum() == pytest.approx(area, rel=0.03)


def test_background_subtraction_finds_each_fish_with_a_subpixel_contour() -> None:
    view = _top_camera()
    model = dense_model(default_model(0.05))
    X = make_state([[0.03, -0.02, 0.0], [0.03, 0.03, 0.05]], [[1.0, 0, 0], [1.0, 0.2, 0]],
                   p_for_length(np.array([[0.2, 0, 0], [-0.3, 0.2, 0]]), 0.05))
    rng = np.random.default_rng(1)
    bg = background(view)
    empty = [render_image(view, model, np.zeros((0, 11)), bg, rng) for _ in range(4)]
    bm = warm_up(empty)
    sil = bm.segment(render_image(view, model, X, bg, rng))
    assert len(sil.blobs) == 2
    cov = coverage(view, model, X)
    from scipy.ndimage import map_coordinates

    for b in sil.blobs:
        at = map_coordinates(cov, [b.contour[:, 1], b.contour[:, 0]], order=1)
        assert abs(np.median(at) - 0.5) < 0.25  # the contour sits on the silhouette's edge
    # an empty frame gives no blob
    assert bm.segment(render_image(view, model, np.zeros((0, 11)), bg, rng)).blobs == []
