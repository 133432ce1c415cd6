"""The spherical lens top: a ball of radius ``R`` whose highest point (apex) is at ``z = apex_z``."""

from __future__ import annotations

import torch

from sim.optics.base import INF, ConvexSet, Vec, solve_quadratic

__all__ = ["Ball"]


class Ball(ConvexSet):
    """Ball centred on the axis at ``z = apex_z - R``.

    Working relative to the apex keeps float32 accurate for ``R = 600`` mm: with
    ``o' = o - apex``, ``|o - c|^2 - R^2 = |o'|^2 + 2 R o'_z`` has no cancellation of two
    numbers near ``R^2``.

    Examples
    --------
    A vertical ray on the axis leaves a ball of apex 12 exactly at z = 12:

    >>> import torch
    >>> b = Ball(600.0, 12.0)
    >>> o = (torch.zeros(1), torch.zeros(1), torch.full((1,), 5.0)); d = (torch.zeros(1), torch.zeros(1), torch.ones(1))
    >>> round(float(b.exit(o, d)[0]), 5)
    7.0
    """

    name = "top"

    def __init__(self, radius: float, apex_z: float):
        self.R = float(radius)
        self.apex_z = float(apex_z)

    def _roots(self, o, d):
        ox, oy, oz = o[0], o[1], o[2] - self.apex_z
        dx, dy, dz = d
        b = ox * dx + oy * dy + oz * dz + self.R * dz          # d . (o - c)
        c = ox * ox + oy * oy + oz * oz + 2.0 * self.R * oz    # |o - c|^2 - R^2
        return solve_quadratic(torch.ones_like(b), b, c)

    def entry(self, o: Vec, d: Vec) -> torch.Tensor:
        t1, t2, real = self._roots(o, d)
        return torch.where(real, t1, torch.full_like(t1, INF))

    def exit(self, o: Vec, d: Vec) -> torch.Tensor:
        t1, t2, real = self._roots(o, d)
        return torch.where(real, t2, torch.full_like(t2, -INF))

    def contains(self, p: Vec, tol: float) -> torch.Tensor:
        x, y, z = p[0], p[1], p[2] - self.apex_z
        # |p - c| - R <= tol, written as (|p-c|^2 - R^2) <= tol (|p-c| + R) ~ 2 R tol.
        return x * x + y * y + z * z + 2.0 * self.R * z <= 2.0 * self.R * tol

    def normal(self, p: Vec) -> Vec:
        inv = 1.0 / self.R
        return p[0] * inv, p[1] * inv, (p[2] - self.apex_z + self.R) * inv
