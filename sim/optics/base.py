"""The small base class every lens surface implements: a convex set bounded by one surface.

A convex lens is the intersection of convex sets (side, top, bottom). Along a ray
``p(t) = o + t d`` each set occupies one interval ``[t_in, t_out]``; the lens occupies
``[max t_in, min t_out]``. So a ray outside the lens enters it at ``max t_in`` (through the
set that attains the maximum) if that point lies in every set, and a ray inside leaves at
``min t_out``. This is exact for convex lenses, needs no per-surface "is the hit within the
surface's bounds" tests, and a ray that has left a convex lens never re-enters it.

Rays are passed structure-of-arrays: ``o = (ox, oy, oz)`` and ``d = (dx, dy, dz)``, each a 1-D
torch tensor of shape (N,), ``d`` unit length. That keeps every elementwise op contiguous.
"""

from __future__ import annotations

import math

import torch

__all__ = ["ConvexSet", "Vec", "INF", "solve_quadratic", "box_interval"]

Vec = tuple  # (x, y, z) of 1-D tensors, each (N,)
INF = math.inf


class ConvexSet:
    """A convex region whose boundary is one lens surface.

    Subclasses implement :meth:`entry`, :meth:`exit`, :meth:`contains` and :meth:`normal`.
    """

    name = "surface"

    def entry(self, o: Vec, d: Vec) -> torch.Tensor:
        """``t`` (N,) where each ray enters the set; ``-inf`` if it starts inside, ``+inf`` if it never enters."""
        raise NotImplementedError

    def exit(self, o: Vec, d: Vec) -> torch.Tensor:
        """``t`` (N,) where each ray leaves the set; ``+inf`` if it never leaves, ``-inf`` if it is never inside."""
        raise NotImplementedError

    def contains(self, p: Vec, tol: float) -> torch.Tensor:
        """Bool (N,): the points lie in the set, up to ``tol`` mm."""
        raise NotImplementedError

    def normal(self, p: Vec) -> Vec:
        """Outward unit normal ``(nx, ny, nz)`` at points ``p`` on the surface."""
        raise NotImplementedError

    def rho_at(self, p: Vec) -> torch.Tensor:
        """Distance of points from the z axis (used for clear apertures)."""
        return torch.sqrt(p[0] * p[0] + p[1] * p[1])


def solve_quadratic(a, b_half, c):
    """Roots ``t1 <= t2`` of ``a t^2 + 2 b_half t + c = 0`` by the cancellation-free formula.

    Returns ``(t1, t2, real)``; where there is no real root (or ``a == 0``) ``real`` is False
    and the roots are 0 (callers mask them).
    """
    disc = b_half * b_half - a * c
    real = (disc >= 0) & (a > 0)
    sq = torch.sqrt(torch.clamp(disc, min=0.0))
    # q = -(b + sign(b) sqrt(disc)): both roots from q without subtracting near-equal numbers.
    q = -(b_half + torch.where(b_half >= 0, sq, -sq))
    safe_a = torch.where(real, a, torch.ones_like(a))
    safe_q = torch.where(q == 0, torch.ones_like(q), q)
    r1 = q / safe_a
    r2 = torch.where(q == 0, torch.zeros_like(q), c / safe_q)
    t1 = torch.minimum(r1, r2)
    t2 = torch.maximum(r1, r2)
    zero = torch.zeros_like(t1)
    return torch.where(real, t1, zero), torch.where(real, t2, zero), real


def box_interval(o: Vec, d: Vec, rho_max: float, z_lo: float, z_hi: float):
    """``(t_lo, t_hi, ok)``: where rays are inside the cylinder ``rho <= rho_max``, ``z_lo <= z <= z_hi``.

    ``t_lo`` is clamped to 0 (rays start at ``t = 0``); ``ok`` is False for rays that miss.
    """
    a = d[0] * d[0] + d[1] * d[1]
    b = o[0] * d[0] + o[1] * d[1]
    c = o[0] * o[0] + o[1] * o[1] - rho_max * rho_max
    t1, t2, real = solve_quadratic(a, b, c)
    axial = a == 0  # parallel to the axis: inside the cylinder for all t, or never
    c_lo = torch.where(real, t1, torch.where(axial & (c <= 0), torch.full_like(t1, -INF), torch.full_like(t1, INF)))
    c_hi = torch.where(real, t2, torch.where(axial & (c <= 0), torch.full_like(t2, INF), torch.full_like(t2, -INF)))
    dz = d[2]
    flat = dz == 0
    safe = torch.where(flat, torch.ones_like(dz), dz)
    s1 = (z_lo - o[2]) / safe
    s2 = (z_hi - o[2]) / safe
    in_slab = (o[2] >= z_lo) & (o[2] <= z_hi)
    ninf, pinf = torch.full_like(s1, -INF), torch.full_like(s1, INF)
    s_lo = torch.where(flat, torch.where(in_slab, ninf, pinf), torch.minimum(s1, s2))
    s_hi = torch.where(flat, torch.where(in_slab, pinf, ninf), torch.maximum(s1, s2))
    t_lo = torch.maximum(torch.maximum(c_lo, s_lo), torch.zeros_like(c_lo))
    t_hi = torch.minimum(c_hi, s_hi)
    return t_lo, t_hi, t_lo <= t_hi
