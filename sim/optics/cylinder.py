"""A cylindrical lens side: the set ``rho <= Rc`` (the plano-sphere scene's edge)."""

from __future__ import annotations

import torch

from sim.optics.base import INF, ConvexSet, Vec, solve_quadratic

__all__ = ["Cylinder"]


class Cylinder(ConvexSet):
    """Infinite solid cylinder of radius ``Rc`` about ``z``.

    Examples
    --------
    >>> import torch
    >>> c = Cylinder(2.0)
    >>> o = (torch.tensor([-5.0]), torch.zeros(1), torch.zeros(1)); d = (torch.ones(1), torch.zeros(1), torch.zeros(1))
    >>> c.entry(o, d).tolist(), c.exit(o, d).tolist()
    ([3.0], [7.0])
    """

    name = "side"

    def __init__(self, radius: float):
        self.Rc = float(radius)

    def _roots(self, o, d):
        a = d[0] * d[0] + d[1] * d[1]
        b = o[0] * d[0] + o[1] * d[1]
        c = o[0] * o[0] + o[1] * o[1] - self.Rc * self.Rc
        return solve_quadratic(a, b, c), c <= 2e-4 * self.Rc  # within ~1e-4 mm counts as inside

    def entry(self, o: Vec, d: Vec) -> torch.Tensor:
        (t1, t2, real), inside = self._roots(o, d)
        # A ray parallel to the axis never crosses the wall: inside forever or never in.
        never = torch.where(inside, torch.full_like(t1, -INF), torch.full_like(t1, INF))
        return torch.where(real, t1, never)

    def exit(self, o: Vec, d: Vec) -> torch.Tensor:
        (t1, t2, real), inside = self._roots(o, d)
        never = torch.where(inside, torch.full_like(t2, INF), torch.full_like(t2, -INF))
        return torch.where(real, t2, never)

    def contains(self, p: Vec, tol: float) -> torch.Tensor:
        return torch.sqrt(p[0] * p[0] + p[1] * p[1]) <= self.Rc + tol

    def normal(self, p: Vec) -> Vec:
        rho = torch.sqrt(p[0] * p[0] + p[1] * p[1]).clamp_min(1e-30)
        return p[0] / rho, p[1] / rho, torch.zeros_like(rho)
