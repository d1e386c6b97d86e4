"""Silhouettes of fish that have no model yet ("claims"), per camera, so that modelled fish do not fit them.

A fish gets its model only in a frame where it is in clear view in the top and the side view (seed 004 §3);
until then its silhouette is in the images all the same. While it is a blob of its own no tracked fish is
associated with it, but when it touches a modelled fish the two make one blob, and the contour lines of the
unmodelled fish would pull the modelled one off its body (eq. 4.2 sums over every contour line of the blob).
Each blob that no tracked fish explains is therefore claimed: its pixels are kept, moved on by the blob's
velocity while it is merged into another blob, and the contour points of tracked fish's blobs inside a
claim are left out of their fits. A claim ends when its fish is modelled, or after `max_age` frames unseen.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from flytrack_host.fish.silhouette import Blob

F64 = NDArray[np.float64]


@dataclass
class Claim:
    pixels: F64  # (N, 2) u, v of the blob when last seen on its own
    centroid: F64
    velocity: F64  # px per frame
    seen: int  # frame index when last seen on its own

    def at(self, k: int) -> tuple[F64, F64]:
        """Predicted pixels and centroid at frame k (constant velocity since last seen)."""
        shift = self.velocity * (k - self.seen)
        return self.pixels + shift, self.centroid + shift


class Claims:
    """The claims of one camera's image."""

    def __init__(self, shape: tuple[int, int], max_age: int = 40, grow_px: int = 2, match_px: float = 25.0) -> None:
        self.shape = shape
        self.max_age = max_age
        self.grow_px = grow_px
        self.match_px = match_px
        self.claims: list[Claim] = []

    def __len__(self) -> int:
        return len(self.claims)

    def mask(self, k: int) -> NDArray[np.uint8] | None:
        """1 where a claim is predicted at frame k (grown by `grow_px`), or None without claims."""
        if not self.claims:
            return None
        H, W = self.shape
        m = np.zeros((H, W), np.uint8)
        for c in self.claims:
            pix, _ = c.at(k)
            uv = np.round(pix).astype(int)
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
            m[uv[ok, 1], uv[ok, 0]] = 1
        if self.grow_px > 0:
            size = 2 * self.grow_px + 1
            m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
        return m

    def update(self, k: int, blobs: list[Blob], free: list[int], modelled: list[int]) -> None:
        """Frame k: `free` blobs no tracked fish explains (claimed, or refreshing the claim they continue),
        `modelled` blobs whose fish got a model this frame (their claims end)."""
        def nearest(c: F64, taken: set[int]) -> int:
            best, bd = -1, self.match_px
            for i, cl in enumerate(self.claims):
                if i in taken:
                    continue
                d = float(np.linalg.norm(cl.at(k)[1] - c))
                if d < bd:
                    best, bd = i, d
            return best

        ended: set[int] = set()
        for j in modelled:
            i = nearest(blobs[j].pixels.mean(axis=0), ended)
            if i >= 0:
                ended.add(i)
        refreshed: set[int] = set()
        new: list[Claim] = []
        for j in free:
            b = blobs[j]
            c = b.pixels.mean(axis=0)
            i = nearest(c, ended | refreshed)
            if i >= 0:
                old = self.claims[i]
                v = (c - old.centroid) / max(k - old.seen, 1)
                self.claims[i] = Claim(b.pixels, c, 0.5 * old.velocity + 0.5 * v if k - old.seen == 1 else v, k)
                refreshed.add(i)
            else:
                new.append(Claim(b.pixels, c, np.zeros(2), k))
        self.claims = [c for i, c in enumerate(self.claims)
                       if i not in ended and k - c.seen <= self.max_age] + new


def unclaimed(contour: F64, mask: NDArray[np.uint8] | None, keep_least: float = 0.3) -> F64:
    """The contour points outside the claimed pixels; the whole contour if a claim would take more than
    1 - `keep_least` of it (a stale claim over a tracked fish must not blind its fit)."""
    if mask is None or len(contour) == 0:
        return contour
    H, W = mask.shape
    uv = np.round(contour).astype(int)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    hit = np.zeros(len(contour), bool)
    hit[ok] = mask[uv[ok, 1], uv[ok, 0]] > 0
    if not np.any(hit) or np.mean(~hit) < keep_least:
        return contour
    return contour[~hit]
