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

__all__ = ["ConvexSet", "Vec", "INF"]

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
