"""Plane surfaces: the lens bottom (a half-space ``z >= z0``) and the imaging plane."""

from __future__ import annotations

import torch

from sim.optics.base import INF, ConvexSet, Vec

__all__ = ["HalfSpaceAbove", "plane_hit"]


class HalfSpaceAbove(ConvexSet):
    """The half-space ``z >= z0``; its surface is the plane ``z = z0`` with outward normal ``-z``.

    Examples
    --------
    >>> import torch
    >>> hs = HalfSpaceAbove(1.0)
    >>> o = (torch.zeros(2), torch.zeros(2), torch.tensor([0.0, 2.0]))
    >>> d = (torch.zeros(2), torch.zeros(2), torch.tensor([1.0, -1.0]))
    >>> hs.entry(o, d).tolist(), hs.exit(o, d).tolist()
    ([1.0, -inf], [inf, 1.0])
    """

    name = "bottom"

    def __init__(self, z0: float, tol: float = 1e-4):
        self.z0 = float(z0)
        # Points within tol of the plane count as on it (rays start on the surface they left).
        self.tol = float(tol)

    def _t(self, o, d):
        dz = d[2]
        safe = torch.where(dz == 0, torch.ones_like(dz), dz)
        return (self.z0 - o[2]) / safe, dz

    def entry(self, o: Vec, d: Vec) -> torch.Tensor:
        t, dz = self._t(o, d)
        inside = o[2] >= self.z0 - self.tol
        # Moving down (or along the plane) the ray is either inside from the start or never enters.
        flat = torch.where(inside, torch.full_like(t, -INF), torch.full_like(t, INF))
        return torch.where(dz > 0, t, flat)

    def exit(self, o: Vec, d: Vec) -> torch.Tensor:
        t, dz = self._t(o, d)
        inside = o[2] >= self.z0 - self.tol
        # Moving up (or along the plane while inside) the ray never leaves the half-space.
        flat = torch.where(inside | (dz > 0), torch.full_like(t, INF), torch.full_like(t, -INF))
        return torch.where(dz < 0, t, flat)

    def contains(self, p: Vec, tol: float) -> torch.Tensor:
        return p[2] >= self.z0 - tol

    def normal(self, p: Vec) -> Vec:
        z = torch.zeros_like(p[0])
        return z, z, torch.full_like(z, -1.0)


def plane_hit(o: Vec, d: Vec, z0: float):
    """Where rays cross the plane ``z = z0`` going forward: ``(x, y, t, ok)``.

    ``ok`` is False for rays parallel to the plane or moving away from it.
    """
    dz = d[2]
    safe = torch.where(dz == 0, torch.ones_like(dz), dz)
    t = (z0 - o[2]) / safe
    ok = (dz != 0) & (t > 0)
    return o[0] + t * d[0], o[1] + t * d[1], t, ok
