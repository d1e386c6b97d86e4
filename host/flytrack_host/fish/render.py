"""Synthetic silhouettes: the shape model's surface projected through each camera, as a back-lit tank
films fish (dark bodies on a bright diffuser, seed 004 §5.1), with sensor noise.

The body is drawn as the union of the convex hulls of consecutive projected cross-section rings; each
hull is the exact image of the short tube between two nearby ellipses, so the union is the silhouette.
Anti-aliased filling at 1/16 px gives partial coverage at the edges, which the sub-pixel contour uses.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from flytrack_host.fish.shape import ShapeModel
from flytrack_host.fish.views import View

F64 = NDArray[np.float64]
_SHIFT = 4  # fixed-point bits for cv2's sub-pixel drawing


def dense_model(model: ShapeModel, n_body: int = 64, n_u: int = 28) -> ShapeModel:
    """The same shape sampled finely, for drawing."""
    s_head = model.s[model.s < 0]
    s = np.concatenate([s_head, np.linspace(0.0, 1.0, n_body)])
    return ShapeModel(s, np.interp(s, model.s, model.a), np.interp(s, model.s, model.b),
                      np.interp(s, model.s, model.d), model.length, n_u)


def coverage(view: View, model: ShapeModel, states: F64, supersample: int = 4) -> NDArray[np.float32]:
    """Fraction of each pixel covered by any fish (H, W) in [0, 1].

    Each fish is filled without anti-aliasing on a `supersample`-times finer grid around it and averaged
    down (cv2 counts a pixel whose centre is on the edge as inside, so the outline is 0.5/supersample px
    too large; 0.125 px at the default)."""
    canvas = np.zeros((view.height, view.width), np.float32)
    states = np.atleast_2d(states)
    states = states[np.all(np.isfinite(states), axis=1)]  # NaN rows: fish not in the tank this frame
    if states.shape[0] == 0:
        return canvas
    S = model.surface(states)  # (F, Ns, Nu, 3)
    uv = view.project(S)  # (F, Ns, Nu, 2)
    F = supersample
    scale = float(1 << _SHIFT)
    for f in range(uv.shape[0]):
        rings = uv[f]
        ok = np.all(np.isfinite(rings), axis=(1, 2))
        if not np.any(ok):
            continue
        pts_all = rings[ok].reshape(-1, 2)
        x0 = max(int(np.floor(pts_all[:, 0].min())) - 1, 0)
        y0 = max(int(np.floor(pts_all[:, 1].min())) - 1, 0)
        x1 = min(int(np.ceil(pts_all[:, 0].max())) + 2, view.width)
        y1 = min(int(np.ceil(pts_all[:, 1].max())) + 2, view.height)
        if x1 <= x0 or y1 <= y0:
            continue  # wholly outside the image
        local = np.zeros(((y1 - y0) * F, (x1 - x0) * F), np.uint8)
        # original pixel i spans [i - 0.5, i + 0.5]; fine pixel j's centre is at (j + 0.5) / F - 0.5
        fine = (rings - np.array([x0, y0]) + 0.5) * F - 0.5
        for i in range(rings.shape[0] - 1):
            if not (ok[i] and ok[i + 1]):
                continue
            hull = cv2.convexHull(np.round(np.concatenate([fine[i], fine[i + 1]]) * scale).astype(np.int32))
            cv2.fillConvexPoly(local, hull, 255, shift=_SHIFT)
        if ok[0]:  # the nose-tip cap
            cv2.fillConvexPoly(local, cv2.convexHull(np.round(fine[0] * scale).astype(np.int32)), 255, shift=_SHIFT)
        small = cv2.resize(local.astype(np.float32) / 255.0, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
        np.maximum(canvas[y0:y1, x0:x1], small, out=canvas[y0:y1, x0:x1])
    return canvas


def background(view: View, level: float = 200.0, seed: int = 0) -> NDArray[np.float32]:
    """A back-lit diffuser: bright, with a gentle vignette and a fixed pattern."""
    h, w = view.height, view.width
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((xx - w / 2) / w) ** 2 + ((yy - h / 2) / h) ** 2
    rng = np.random.default_rng(seed)
    pattern = cv2.GaussianBlur(rng.normal(0, 4.0, (h, w)).astype(np.float32), (0, 0), 6)
    return level * (1.0 - 0.35 * r2) + pattern


def render_image(view: View, model: ShapeModel, states: F64, bg: NDArray[np.float32], rng: np.random.Generator,
                 fish_level: float = 45.0, noise: float = 3.0, flicker: float = 0.0) -> NDArray[np.uint8]:
    """One 8-bit camera frame: background darkened where fish are, plus Gaussian sensor noise."""
    cov = coverage(view, model, states)
    gain = 1.0 + flicker * rng.standard_normal()
    img = (bg * gain) * (1.0 - cov) + fish_level * cov + rng.normal(0.0, noise, cov.shape).astype(np.float32)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def render_sequence(views: Sequence[View], model: ShapeModel, truth: F64, rng: np.random.Generator,
                    n_background: int = 5, noise: float = 3.0) -> list[list[NDArray[np.uint8]]]:
    """Frames per camera: `n_background` empty frames first (to seed the background model, as the seed's
    sequences start with background images), then one frame per row of truth (T, F, 11)."""
    dm = dense_model(model)
    out: list[list[NDArray[np.uint8]]] = []
    for ci, v in enumerate(views):
        bg = background(v, seed=ci)
        frames = [render_image(v, dm, np.zeros((0, 11)), bg, rng, noise=noise) for _ in range(n_background)]
        frames += [render_image(v, dm, truth[k], bg, rng, noise=noise) for k in range(truth.shape[0])]
        out.append(frames)
    return out
