"""The fish shape model of seed 004 §3: a polynomial midline in a head-fixed body frame (eqs 3.1-3.2),
elliptical cross-sections in planes normal to the midline found by curve framing (eqs 3.4-3.7).

Every function is batched over B states so the fit can score many candidate poses in one NumPy pass.

Conventions (metres, world z up):
- state X = [r (3), h (3, unit), p (5)]: r the centre of the head, h the heading (head centre -> nose).
- body frame (eq. 3.2): columns h, g x h, h x (g x h) with g = (0, 0, 1): no roll (assumption 3.2).
- midline (eq. 3.1) runs from the head centre (s = 0) to the tail (s = 1). The seed writes f1 = p1 s + p2 s^2
  with "p1 the length of the fish"; the tail lies behind the head, so here f1 = -(p1 s + p2 s^2) and p1 > 0
  is the head-to-tail length. f2 = p3 s^2 + p4 s^3 + p5 s^4 (lateral bend), f3 = 0.
- the head (nose to head centre) does not bend (assumption 3.3): for s < 0 the midline is the straight
  continuation along h, f1 = -p1 s, f2 = 0, so it is C1 at s = 0; the nose tip is at s = -nose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
G = np.array([0.0, 0.0, 1.0])
STATE_DIM = 11
N_P = 5


def heading_from_angles(yaw: F64 | float, pitch: F64 | float) -> F64:
    """Unit heading from yaw (about z, from +x) and pitch (up positive), radians."""
    yaw = np.asarray(yaw, dtype=float)
    pitch = np.asarray(pitch, dtype=float)
    return np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=-1)


def angles_from_heading(h: F64) -> tuple[F64, F64]:
    h = np.asarray(h, dtype=float)
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    return np.arctan2(h[..., 1], h[..., 0]), np.arcsin(np.clip(h[..., 2], -1.0, 1.0))


def body_axes(h: F64) -> F64:
    """Heading (B,3) -> rotation (B,3,3) whose columns are h, g x h, h x (g x h) (eq. 3.2)."""
    h = np.atleast_2d(np.asarray(h, dtype=float))
    h = h / _norm(h)
    y = _g_cross(h)
    n = _norm(y)
    y = y / np.where(n > 1e-12, n, 1.0)  # a vertical heading has no defined pitch axis; keep it finite
    z = _cross(h, y)
    return np.stack([h, y, z], axis=2)


# The fit evaluates the surface hundreds of thousands of times per run on small arrays, where np.cross and
# np.linalg.norm cost more in argument handling than in arithmetic; these do the same operations in the
# same order (the results are bit for bit those of np.cross / np.linalg.norm).
def _norm(a: F64) -> F64:
    """Euclidean norm over the last axis, kept as a length-1 axis."""
    return np.sqrt(np.add.reduce(a * a, axis=-1, keepdims=True))


def _cross(a: F64, b: F64) -> F64:
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    np.subtract(a1 * b2, a2 * b1, out=out[..., 0])
    np.subtract(a2 * b0, a0 * b2, out=out[..., 1])
    np.subtract(a0 * b1, a1 * b0, out=out[..., 2])
    return out


def _g_cross(t: F64) -> F64:
    """G x t for G = (0, 0, 1): (-t_y, t_x, 0)."""
    out = np.zeros(t.shape)
    np.negative(t[..., 1], out=out[..., 0])
    out[..., 1] = t[..., 0]
    return out


def midline_body(p: F64, s: F64, second: bool = True) -> tuple[F64, F64, F64 | None]:
    """Midline f(s) in the body frame and its first and second s-derivatives, each (B, Ns, 3) (the second
    None when `second` is False: the surface and the arclength do not need it)."""
    p = np.atleast_2d(np.asarray(p, dtype=float))
    s = np.asarray(s, dtype=float)
    sp = np.clip(s, 0.0, None)  # the bending polynomial acts on the body only (s >= 0)
    sp2 = sp**2
    sp3 = sp**3
    p1, p2, p3, p4, p5 = (p[:, i : i + 1] for i in range(5))
    f = np.zeros((p.shape[0], s.size, 3))
    df = np.zeros_like(f)
    f[:, :, 0] = -(p1 * s + p2 * sp2)
    f[:, :, 1] = p3 * sp2 + p4 * sp3 + p5 * sp**4
    df[:, :, 0] = -(p1 + 2.0 * p2 * sp)
    df[:, :, 1] = 2.0 * p3 * sp + 3.0 * p4 * sp2 + 4.0 * p5 * sp3
    if not second:
        return f, df, None
    d2f = np.zeros_like(f)
    body = s >= 0
    d2f[:, :, 0] = np.where(body, -2.0 * p2, 0.0)
    d2f[:, :, 1] = np.where(body, 2.0 * p3 + 6.0 * p4 * sp + 12.0 * p5 * sp2, 0.0)
    return f, df, d2f


def midline_world(X: F64, s: F64) -> tuple[F64, F64]:
    """Eq. 3.2: states (B,11) -> midline points m(s) (B,Ns,3) and unit tangents t(s) (B,Ns,3)."""
    X = np.atleast_2d(np.asarray(X, dtype=float))
    Rb = body_axes(X[:, 3:6])
    f, df, _ = midline_body(X[:, 6:11], s, second=False)
    m = X[:, None, 0:3] + np.einsum("bij,bsj->bsi", Rb, f)
    t = np.einsum("bij,bsj->bsi", Rb, df)
    t /= _norm(t)
    return m, t


def section_frames(t: F64) -> tuple[F64, F64]:
    """Curve framing (eq. 3.4): x(s) = g x t (normalised), y(s) = t x x. Inputs/outputs (..., 3)."""
    x = _g_cross(t)
    n = _norm(x)
    x = x / np.where(n > 1e-12, n, 1.0)
    y = _cross(t, x)
    return x, y


@dataclass
class ShapeModel:
    """Cross-section sizes a(s) (half-width, seen from above), b(s) (half-height), d(s) (vertical offset
    of the ellipse centre along y(s)) at stations s; s < 0 is the rigid head, s = -nose the nose tip."""

    s: F64
    a: F64
    b: F64
    d: F64
    length: float  # p1 of the straight fish (head centre to tail), metres
    n_u: int = 12  # points around each ellipse for the fit's surface
    _u: F64 = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.s = np.asarray(self.s, dtype=float)
        self.a = np.asarray(self.a, dtype=float)
        self.b = np.asarray(self.b, dtype=float)
        self.d = np.asarray(self.d, dtype=float)
        if not (self.s.shape == self.a.shape == self.b.shape == self.d.shape) or self.s.ndim != 1:
            raise ValueError("shape model: s, a, b, d must be 1-D arrays of the same length")
        if np.any(np.diff(self.s) <= 0):
            raise ValueError("shape model: stations s must increase")
        self._u = np.linspace(0.0, 2.0 * np.pi, self.n_u, endpoint=False)

    @property
    def nose(self) -> float:
        return float(-self.s[0])

    def copy_with(self, a: F64, b: F64, d: F64) -> ShapeModel:
        return ShapeModel(self.s.copy(), np.asarray(a), np.asarray(b), np.asarray(d), self.length, self.n_u)

    def surface(self, X: F64, u: F64 | None = None) -> F64:
        """Eq. 3.7: S(s,u) = m + a cos(u) x + (b sin(u) + d) y for states (B,11) -> (B, Ns, Nu, 3)."""
        u = self._u if u is None else np.asarray(u, dtype=float)
        m, t = midline_world(X, self.s)
        x, y = section_frames(t)
        cu, su = np.cos(u), np.sin(u)
        return (
            m[:, :, None, :]
            + (self.a[None, :, None, None] * cu[None, None, :, None]) * x[:, :, None, :]
            + (self.b[None, :, None, None] * su[None, None, :, None] + self.d[None, :, None, None])
            * y[:, :, None, :]
        )


def default_model(length: float = 0.05, n_body: int = 16, n_head: int = 3, n_u: int = 8) -> ShapeModel:
    """A danio-like shape (giant danio: about 6-7 cm long, 1.5 cm deep): widest at the head centre (so the
    largest circle inside the top silhouette is centred there, as the seed's model generation assumes),
    tapering to a narrow caudal peduncle. Used as the synthetic truth and as a starting model."""
    nose = 0.22  # nose to head centre, as a fraction of p1
    sh = -nose * np.cos(np.linspace(0.0, np.pi / 2, n_head, endpoint=False))  # denser near the tip
    sb = np.linspace(0.0, 1.0, n_body)
    s = np.concatenate([sh, sb])
    L = length
    # head: an elliptic nose cap; body: smooth taper to 6% of the maximum at the tail
    # the widest section is at the head centre, with a clear maximum on both sides of it
    head = np.sqrt(np.clip(1.0 - (s / nose) ** 2, 0.0, 1.0)) * (1.0 - 0.3 * np.abs(s) / nose)
    body = 0.06 + 0.94 * (1.0 - s) ** 1.3 * (1.0 + 0.5 * s)
    prof = np.where(s < 0, 0.15 + 0.85 * head, np.minimum(body, 1.0))
    prof[0] = 0.15
    a = 0.075 * L * prof  # half-width about 3.7 mm for 5 cm
    b = 0.13 * L * np.where(s < 0, prof, np.minimum(1.0, 0.2 + 0.8 * (1.0 - s) ** 0.9 * (1.0 + 0.9 * s)))
    d = -0.01 * L * np.clip(1.0 - np.abs(s - 0.3) / 0.7, 0.0, 1.0)  # belly slightly lower mid-body
    return ShapeModel(s=s, a=a, b=b, d=d, length=L, n_u=n_u)


_GL: dict[int, tuple[F64, F64]] = {}


def arclength(p: F64, n: int = 24) -> F64:
    """Length of the body midline (s in [0, 1]) for p (B,5), by Gauss-Legendre quadrature."""
    if n not in _GL:
        _GL[n] = np.polynomial.legendre.leggauss(n)
    xg, wg = _GL[n]
    s = 0.5 * (xg + 1.0)
    _, df, _ = midline_body(p, s, second=False)
    return 0.5 * (np.linalg.norm(df[:, :, :2], axis=2) @ wg)


def p_for_length(bend: F64, length: float) -> F64:
    """Midline parameters (p1, 0, p3, p4, p5) with the given bend (p3..p5 as fractions of the length) whose
    arclength is `length`: a swimming fish keeps its length, so a bend shortens its extent along h."""
    bend = np.atleast_2d(np.asarray(bend, dtype=float))
    out = np.zeros((bend.shape[0], 5))
    out[:, 2:] = bend * length
    lo = np.full(bend.shape[0], 0.05 * length)
    hi = np.full(bend.shape[0], length)
    for _ in range(40):  # bisection, vectorised over the batch (arclength grows with p1)
        mid = 0.5 * (lo + hi)
        out[:, 0] = mid
        long_ = arclength(out) > length
        hi = np.where(long_, mid, hi)
        lo = np.where(long_, lo, mid)
    out[:, 0] = 0.5 * (lo + hi)
    return out


def make_state(r: F64, h: F64, p: F64) -> F64:
    r = np.atleast_2d(np.asarray(r, dtype=float))
    h = np.atleast_2d(np.asarray(h, dtype=float))
    h = h / np.linalg.norm(h, axis=1, keepdims=True)
    p = np.atleast_2d(np.asarray(p, dtype=float))
    return np.concatenate([r, h, p], axis=1)
