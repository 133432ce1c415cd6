"""The lens as one convex body: entry and exit points of rays, with the surface that was hit.

Surface ids: ``SIDE = 0``, ``TOP = 1``, ``BOTTOM = 2``.
"""

from __future__ import annotations

import torch

from sim.optics.base import Vec, box_interval
from sim.optics.conic import ConicTop
from sim.optics.cylinder import Cylinder
from sim.optics.plane import HalfSpaceAbove
from sim.optics.sphere import Ball
from sim.optics.torus import SweptArc

__all__ = ["SIDE", "TOP", "BOTTOM", "LensBody"]

SIDE, TOP, BOTTOM = 0, 1, 2


class LensBody:
    """Intersection of the side, top and bottom convex sets of a :class:`sim.scene.Lens`.

    Parameters
    ----------
    lens : sim.scene.Lens
    iterations : int
        Newton iterations of the swept-arc solve.
    tol : float
        Tolerance (mm) of the "point lies in every set" test.
    """

    def __init__(self, lens, iterations: int = 10, tol: float = 1e-3):
        self.lens = lens
        if lens.is_arc:
            self.side = SweptArc(lens.arc_radius, lens.centre_rho, lens.centre_z, lens.bottom_z, lens.rim_z,
                                 iterations=iterations)
            rho_max = self.side.rho_max
        else:
            self.side = Cylinder(lens.cylinder_radius)
            rho_max = lens.cylinder_radius
        # A sphere keeps the ball (the paper's case 3, and the path every existing scene takes).
        self.top = (Ball(lens.top_radius, lens.apex_z) if lens.top_conic == 0.0
                    else ConicTop(lens.top_radius, lens.apex_z, lens.top_conic))
        self.bottom = HalfSpaceAbove(lens.bottom_z)
        self.sets = (self.side, self.top, self.bottom)
        self.tol = float(tol)
        margin = 1e-3
        self.box = (rho_max + margin, lens.bottom_z - margin, lens.apex_z + margin)

    def enter(self, o: Vec, d: Vec, box=None):
        """Rays outside the lens: ``(t, surface_id, hit, unconverged)``, each (N,).

        ``unconverged`` marks rays whose swept-arc solve did not converge (counted as misses).
        ``box`` is :func:`box_interval` of these rays if the caller has it already.
        """
        return self.enter_capped(o, d, box)[:4]

    def enter_capped(self, o: Vec, d: Vec, box=None, cap: int | None = None):
        """:meth:`enter` plus ``unfinished``: with ``cap``, the swept-arc solve takes at most ``cap``
        Newton steps on every ray and ``unfinished`` marks the rays it left short of the root
        (see :meth:`sim.optics.torus.SweptArc.entry_capped`); None without a cap or a swept arc.
        """
        t_lo, t_hi, ok = box if box is not None else box_interval(o, d, *self.box)
        unfinished = None
        if isinstance(self.side, SweptArc):
            e0, unconverged, unfinished = self.side.entry_capped(o, d, t_lo, t_hi, cap=cap)
        else:
            e0, unconverged = self.side.entry(o, d), torch.zeros_like(ok)
        e1 = self.top.entry(o, d)
        e2 = self.bottom.entry(o, d)
        t = torch.maximum(torch.maximum(e0, e1), e2)
        sid = torch.where(e0 >= torch.maximum(e1, e2), SIDE, torch.where(e1 >= e2, TOP, BOTTOM))
        hit = ok & torch.isfinite(t) & (t > 0)
        ts = torch.where(hit, t, torch.zeros_like(t))
        p = (o[0] + ts * d[0], o[1] + ts * d[1], o[2] + ts * d[2])
        inside = self.side.contains(p, self.tol) & self.top.contains(p, self.tol) & self.bottom.contains(p, self.tol)
        hit = hit & inside
        if unfinished is not None:
            unfinished = unfinished & ok
        return torch.where(hit, t, torch.zeros_like(t)), sid, hit, unconverged & ok, unfinished

    def leave(self, o: Vec, d: Vec):
        """Rays inside the lens: ``(t, surface_id, ok)`` of the exit point."""
        return self.leave_capped(o, d)[:3]

    def leave_capped(self, o: Vec, d: Vec, cap: int | None = None):
        """:meth:`leave` plus ``unfinished`` (as in :meth:`enter_capped`)."""
        t_lo, t_hi, ok = box_interval(o, d, *self.box)
        x1 = self.top.exit(o, d)
        x2 = self.bottom.exit(o, d)
        x12 = torch.minimum(x1, x2)
        unfinished = None
        if isinstance(self.side, SweptArc):
            # The side's Newton starts at the nearer of the box's far end and the other exits:
            # rays leaving through the top (nearly all) need no step.
            x0, unfinished = self.side.exit_capped(o, d, t_lo, t_hi, start=torch.minimum(t_hi, x12), cap=cap)
        else:
            x0 = self.side.exit(o, d)
        t = torch.minimum(x0, x12)
        sid = torch.where(x0 <= x12, SIDE, torch.where(x1 <= x2, TOP, BOTTOM))
        good = torch.isfinite(t) & (t >= 0)
        return torch.where(good, t, torch.zeros_like(t)), sid, good, unfinished

    def normal(self, p: Vec, sid) -> Vec:
        """Outward unit normals at points ``p`` on the surfaces ``sid``."""
        n0 = self.side.normal(p)
        n1 = self.top.normal(p)
        n2 = self.bottom.normal(p)
        s0, s1 = sid == SIDE, sid == TOP
        return tuple(torch.where(s0, a, torch.where(s1, b, c)) for a, b, c in zip(n0, n1, n2))
