"""A conic lens top: the solid under a surface of revolution ``z = apex - sag(rho)``.

``sag(rho) = rho^2 / (R (1 + sqrt(1 - (1 + k) rho^2 / R^2)))`` is the optician's conic of apex
radius ``R`` and conic constant ``k``: ``k = 0`` a sphere (the paper's top, :class:`sim.optics.sphere.Ball`),
``-1 < k < 0`` a prolate ellipsoid (flatter toward the rim than the sphere), ``k = -1`` a
paraboloid, ``k < -1`` a hyperboloid (tending far out to a cone whose surface rises at slope
``1 / sqrt(-1 - k)``), ``k > 0`` an oblate ellipsoid (steeper toward the rim).

With ``w = apex_z - z`` (depth below the apex) every such surface is the quadric

    Q(p) = rho^2 + e w^2 - 2 R w = 0,    e = 1 + k,

and the lens material is the convex set ``Q <= 0`` (for ``e < 0`` one sheet of a two-sheeted
hyperboloid: the plane ``w = R / e`` separates the sheets, and the set is cut to the apex's
side of it). Along a ray ``Q`` is a quadratic in ``t``, so entry and exit are closed-form
(cancellation-free quadratic formula, computed relative to the apex like the ball so that
``R = 600`` mm keeps float32 accurate). A sphere (``k = 0``) gives exactly :class:`Ball`'s
intervals; the tests check that, and points on the surface against the sag formula.
"""

from __future__ import annotations

import torch

from sim.optics.base import INF, ConvexSet, Vec, solve_quadratic

__all__ = ["ConicTop", "conic_sag"]


def conic_sag(rho, radius: float, conic: float):
    """Sag ``apex_z - z`` of the conic at radii ``rho`` (numpy or torch; NaN past an ellipsoid's rim).

    Examples
    --------
    >>> import numpy as np
    >>> round(float(conic_sag(np.array(3.0), 5.0, 0.0)), 12)   # sphere: 5 - sqrt(25 - 9)
    1.0
    >>> float(conic_sag(np.array(2.0), 1.0, -1.0))             # paraboloid: rho^2 / (2 R)
    2.0
    """
    lib = torch if isinstance(rho, torch.Tensor) else __import__("numpy")
    e = 1.0 + conic
    arg = 1.0 - e * rho * rho / (radius * radius)
    return rho * rho / (radius * (1.0 + lib.sqrt(arg)))


class ConicTop(ConvexSet):
    """The convex set ``Q <= 0`` (see the module docstring) with apex at ``z = apex_z``.

    Parameters
    ----------
    radius : float
        Apex radius of curvature ``R`` (> 0, convex).
    apex_z : float
    conic : float
        Conic constant ``k`` (0: sphere).

    Examples
    --------
    A vertical ray on the axis leaves at the apex whatever the conic:

    >>> import torch
    >>> top = ConicTop(50.0, 12.0, -2.0)
    >>> o = (torch.zeros(1), torch.zeros(1), torch.full((1,), 5.0)); d = (torch.zeros(1), torch.zeros(1), torch.ones(1))
    >>> round(float(top.exit(o, d)[0]), 5)
    7.0
    """

    name = "top"

    def __init__(self, radius: float, apex_z: float, conic: float = 0.0):
        if not radius > 0:
            raise ValueError(f"ConicTop: radius must be > 0, got {radius}")
        self.R = float(radius)
        self.apex_z = float(apex_z)
        self.k = float(conic)
        self.e = 1.0 + self.k
        # For a hyperboloid (e < 0): the plane between the two sheets, z = apex - R / e.
        self.z_cap = self.apex_z - self.R / self.e if self.e < 0 else INF

    def _interval(self, o: Vec, d: Vec):
        """``(lo, hi)`` (N,) of the set along each ray; ``lo > hi`` where the ray misses it."""
        e, R = self.e, self.R
        ox, oy, dz = o[0], o[1], d[2]
        w0 = self.apex_z - o[2]
        a = d[0] * d[0] + d[1] * d[1] + e * dz * dz
        b = ox * d[0] + oy * d[1] - (e * w0 - R) * dz
        c = ox * ox + oy * oy + (e * w0 - 2.0 * R) * w0
        ninf, pinf = torch.full_like(c, -INF), torch.full_like(c, INF)
        # a > 0: [t1, t2] (solve_quadratic masks a <= 0 as no real roots).
        t1, t2, real = solve_quadratic(a, b, c)
        lo = torch.where(real, t1, pinf)
        hi = torch.where(real, t2, ninf)
        if e <= 0:
            # a == 0 (vertical ray on a paraboloid, or a ray along a hyperboloid's asymptote):
            # Q = 2 b t + c is linear.
            lin = a == 0
            safe_b = torch.where(b == 0, torch.ones_like(b), b)
            root = -c / (2.0 * safe_b)
            lo = torch.where(lin, torch.where(b < 0, root, torch.where((b == 0) & (c <= 0), ninf,
                                                                          torch.where(b == 0, pinf, ninf))), lo)
            hi = torch.where(lin, torch.where(b > 0, root, torch.where((b == 0) & (c <= 0), pinf,
                                                                          torch.where(b == 0, ninf, pinf))), hi)
        if e < 0:
            # a < 0: Q <= 0 outside the roots, (-inf, r1] and [r2, inf), one piece per sheet
            # (or the whole line without real roots); the sheet half-space z <= z_cap keeps one.
            neg = a < 0
            disc = b * b - a * c
            sq = torch.sqrt(torch.clamp(disc, min=0.0))
            safe_a = torch.where(neg, a, -torch.ones_like(a))
            r_a = (-b + sq) / safe_a  # a < 0: the smaller root
            r_b = (-b - sq) / safe_a
            r1, r2 = torch.minimum(r_a, r_b), torch.maximum(r_a, r_b)
            two = neg & (disc >= 0)
            up = dz > 0  # moving up: the half-space is (-inf, th]; the lower piece is the one kept
            lo = torch.where(neg, torch.where(two & ~up, r2, ninf), lo)
            hi = torch.where(neg, torch.where(two & up, r1, pinf), hi)
            # Intersect with the half-space z <= z_cap.
            flat = dz == 0
            th = (self.z_cap - o[2]) / torch.where(flat, torch.ones_like(dz), dz)
            below = o[2] <= self.z_cap
            h_lo = torch.where(flat, torch.where(below, ninf, pinf), torch.where(up, ninf, th))
            h_hi = torch.where(flat, torch.where(below, pinf, ninf), torch.where(up, th, pinf))
            lo, hi = torch.maximum(lo, h_lo), torch.minimum(hi, h_hi)
        return lo, hi

    def entry(self, o: Vec, d: Vec) -> torch.Tensor:
        lo, hi = self._interval(o, d)
        return torch.where(lo <= hi, lo, torch.full_like(lo, INF))

    def exit(self, o: Vec, d: Vec) -> torch.Tensor:
        lo, hi = self._interval(o, d)
        return torch.where(lo <= hi, hi, torch.full_like(hi, -INF))

    def _q_grad(self, p: Vec):
        w = self.apex_z - p[2]
        rho2 = p[0] * p[0] + p[1] * p[1]
        q = rho2 + (self.e * w - 2.0 * self.R) * w
        gz = self.R - self.e * w  # dQ/dz / 2
        return q, w, torch.sqrt(rho2 + gz * gz), gz

    def contains(self, p: Vec, tol: float) -> torch.Tensor:
        q, w, g, _ = self._q_grad(p)
        # Q <= tol |grad Q| (|grad Q| = 2 g): within ~tol mm of the surface counts as inside.
        ok = q <= 2.0 * tol * g
        if self.e < 0:
            ok = ok & (p[2] <= self.z_cap)
        return ok

    def normal(self, p: Vec) -> Vec:
        _, _, g, gz = self._q_grad(p)
        inv = 1.0 / g.clamp_min(1e-30)
        return p[0] * inv, p[1] * inv, gz * inv
