"""Silhouettes from video: background subtraction with a running average (seed 004 eq. 5.1),
B_{k+1} = B_k (1 - alpha) + alpha I_{k+1}, with alpha high (0.05) while the tank is empty and low (0.0001)
once fish are present (Table 2); blobs by connected components; the occluding contour at sub-pixel
precision (each boundary pixel moved along the image gradient to the half-contrast level).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
ALPHA_START = 0.05
ALPHA_END = 0.0001


@dataclass
class Blob:
    label: int
    area: int
    bbox: tuple[int, int, int, int]  # x, y, w, h
    pixels: F64  # (N, 2) u, v of the foreground pixels
    contour: F64  # (M, 2) sub-pixel points on the occluding contour


@dataclass
class Silhouettes:
    mask: NDArray[np.uint8]  # 0/1 foreground
    fg: NDArray[np.float32]  # foreground strength in [0, 1] (0.5 = the silhouette's edge)
    labels: NDArray[np.int32]
    blobs: list[Blob]


class BackgroundModel:
    """Eq. 5.1's running average for one camera. `alpha` falls from ALPHA_START to ALPHA_END once fish are
    present (`fish_present()`); `contrast` is the least relative darkening taken as a fish's interior."""

    def __init__(self, first: NDArray[np.uint8], contrast: float = 0.5, min_area: int = 12) -> None:
        self.B = first.astype(np.float32)
        self.alpha = ALPHA_START
        self.contrast = contrast
        self.darkening: float | None = None
        self.min_area = min_area

    def fish_present(self) -> None:
        self.alpha = ALPHA_END

    def update(self, image: NDArray[np.uint8]) -> None:
        cv2.accumulateWeighted(image.astype(np.float32), self.B, self.alpha)

    def segment(self, image: NDArray[np.uint8], update: bool = True) -> Silhouettes:
        img = image.astype(np.float32)
        # fish are darker than the back-lit background: relative darkening D, scaled by a fish interior's
        # darkening (a high percentile of the clearly dark pixels) so that fg = 0.5 at a half-covered pixel
        D = (self.B - img) / np.maximum(self.B, 1.0)
        rough = D > self.contrast * 0.5
        dark = D[rough]
        if dark.size > 20:
            est = float(np.percentile(dark, 90))
            self.darkening = est if self.darkening is None else 0.7 * self.darkening + 0.3 * est
        fg = np.clip(D * (1.0 / max(self.darkening or 0.5, 0.05)), 0.0, 1.0)
        mask = (fg > 0.5).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        blobs: list[Blob] = []
        H, W = mask.shape
        for j in range(1, n):
            x, y, w, h, area = (int(v) for v in stats[j])
            if area < self.min_area:
                mask[labels == j] = 0
                continue
            sub = labels[y:y + h, x:x + w] == j
            vv, uu = np.nonzero(sub)
            pixels = np.stack([uu + x, vv + y], axis=1).astype(float)
            # a 2-pixel margin around the blob for the gradient of the sub-pixel step
            x0, y0, x1, y1 = max(x - 2, 0), max(y - 2, 0), min(x + w + 2, W), min(y + h + 2, H)
            win = fg[y0:y1, x0:x1]
            gy, gx = np.gradient(win)
            sub_w = labels[y0:y1, x0:x1] == j
            contour = _subpixel_contour(sub_w, win, gx, gy) + np.array([x0, y0], float)
            blobs.append(Blob(j, area, (x, y, w, h), pixels, contour))
        if update:
            # only the background is updated, so a fish that stops does not fade into it
            B_new = self.B.copy()
            cv2.accumulateWeighted(img, B_new, self.alpha)
            keep = cv2.dilate(mask, np.ones((5, 5), np.uint8)) > 0
            B_new[keep] = self.B[keep]
            self.B = B_new
        return Silhouettes(mask, fg, labels, blobs)


def _subpixel_contour(sub: NDArray[np.bool_], fg: NDArray[np.float32], gx: NDArray[np.float32],
                      gy: NDArray[np.float32]) -> F64:
    """Boundary pixels of `sub` moved along the gradient of fg to the 0.5 crossing, in window coordinates."""
    cs, _ = cv2.findContours(sub.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not cs:
        return np.zeros((0, 2))
    c = max(cs, key=len).reshape(-1, 2)
    u = c[:, 0]
    v = c[:, 1]
    g = np.stack([gx[v, u], gy[v, u]], axis=1)
    gn = np.linalg.norm(g, axis=1)
    ok = gn > 1e-3
    # first-order step from the boundary pixel to the 0.5 level along the gradient (which points inwards)
    step = np.zeros(len(u))
    step[ok] = (0.5 - fg[v[ok], u[ok]]) / gn[ok]
    step = np.clip(step, -1.0, 1.0)
    dirs = np.zeros((len(u), 2))
    dirs[ok] = g[ok] / gn[ok, None]
    return np.stack([u, v], axis=1) + dirs * step[:, None]


def warm_up(frames: list[NDArray[np.uint8]], contrast: float = 0.5) -> BackgroundModel:
    """A background model from fish-free frames (the first is B_0; each later one updates with alpha 0.05)."""
    if not frames:
        raise ValueError("background: need at least one frame")
    bm = BackgroundModel(frames[0], contrast)
    for f in frames[1:]:
        bm.update(f)
    bm.fish_present()
    return bm
