"""Measurement-to-target association by the generalised midline-to-silhouette distance (seed 004 eq. 4.1):
a target's projected midline is scored against each silhouette by the sum over midline points of the
distance to the nearest silhouette pixel; each target takes the silhouette with the least score. Several
targets may take the same silhouette: that is an occlusion, and they are then fitted together.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from flytrack_host.fish.silhouette import Blob

F64 = NDArray[np.float64]


def midline_scores(midlines_uv: Sequence[F64], blobs: Sequence[Blob], max_pixels: int = 4000) -> F64:
    """Eq. 4.1's score sum_s min_i ||u_i - u_hat_t(s)|| for every target t (rows) and blob j (columns), px.
    A midline point outside the image (NaN) does not count."""
    scores = np.full((len(midlines_uv), len(blobs)), np.inf)
    for j, b in enumerate(blobs):
        pix = b.pixels
        if len(pix) > max_pixels:  # a thinned grid is as good for a nearest-pixel distance of a few px
            pix = pix[:: int(np.ceil(len(pix) / max_pixels))]
        tree = cKDTree(pix)
        for t, m in enumerate(midlines_uv):
            ok = np.all(np.isfinite(m), axis=1)
            if not np.any(ok):
                continue
            d, _ = tree.query(m[ok])
            scores[t, j] = float(d.sum()) * len(m) / ok.sum()
    return scores


def associate(midlines_uv: Sequence[F64], blobs: Sequence[Blob], gate_px: float) -> list[int]:
    """Blob index for each target (eq. 4.1's argmin), or -1 when even the best blob is farther than
    `gate_px` per midline point on average (the target is not seen in this camera: out of view, hidden
    in nothing the camera segmented, or left the tank)."""
    if not blobs:
        return [-1] * len(midlines_uv)
    S = midline_scores(midlines_uv, blobs)
    out = []
    for t, m in enumerate(midlines_uv):
        j = int(np.argmin(S[t]))
        out.append(j if S[t, j] <= gate_px * len(m) else -1)
    return out
