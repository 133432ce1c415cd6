"""The swept-arc lens side: the outer half of a circle swept about ``z`` (part of a torus).

In the meridian plane the side is ``rho = g(z) = rho_c + sqrt(r1^2 - (z - z_c)^2)`` for ``z``
between the lens bottom and the rim where it meets the top. ``g`` is concave, so the set
``rho <= g(z)`` is convex. Outside ``[z_lo, z_hi]`` we extend ``g`` by its tangent lines (still
concave; the lens's other surfaces cut those parts away), which keeps the set convex and
``g`` finite and C1 everywhere.

Along a ray, ``S(t) = rho(t) - g(z(t))`` is then a convex function of ``t`` (``rho`` of a line
is convex, ``-g`` of an affine argument is convex). Newton's method on a convex function
started left of its first root (where ``S > 0``, ``S' < 0``) moves monotonically right onto
that root and never jumps past it; started right of the last root it moves monotonically
left onto the last root. That is our robust solve: a safeguarded Newton iteration whose
bracket is the lens's bounding box, with no possibility of converging to the wrong root.
If ``S' >= 0`` while ``S > 0`` on the left-hand iteration, the ray misses the set.
:func:`sim.optics.quartic.torus_roots` cross-checks it against the full quartic.
"""

from __future__ import annotations

import math

import torch

from sim.optics.base import INF, ConvexSet, Vec, box_interval

__all__ = ["SweptArc"]


class SweptArc(ConvexSet):
    """The set ``rho <= g(z)`` of an arc of radius ``r1`` centred at ``(rho_c, z_c)``.

    Parameters
    ----------
    r1, rho_c, z_c : float
        Arc radius and centre in the meridian plane (mm).
    z_lo, z_hi : float
        The ``z`` range where the side is a real surface (lens bottom to rim).
    iterations : int
        Newton iterations per solve (convergence is checked; see :meth:`entry_status`).

    Examples
    --------
    A horizontal ray at the arc centre's height meets the side at ``rho_c + r1``:

    >>> import torch
    >>> s = SweptArc(13.5, 22.5, 6.0, 1.0, 11.0)
    >>> o = (torch.tensor([50.0]), torch.zeros(1), torch.full((1,), 6.0))
    >>> d = (torch.tensor([-1.0]), torch.zeros(1), torch.zeros(1))
    >>> round(float(s.entry(o, d, torch.zeros(1), torch.full((1,), 100.0))[0]), 4)
    14.0
    """

    name = "side"

    def __init__(self, r1: float, rho_c: float, z_c: float, z_lo: float, z_hi: float, iterations: int = 10,
                 tol: float = 1e-4):
        if not (abs(z_lo - z_c) < r1 and abs(z_hi - z_c) < r1 and z_lo < z_hi):
            raise ValueError(f"SweptArc: z range [{z_lo}, {z_hi}] must lie strictly inside the arc's "
                             f"[{z_c - r1}, {z_c + r1}]")
        self.r1, self.rho_c, self.z_c = float(r1), float(rho_c), float(z_c)
        self.z_lo, self.z_hi = float(z_lo), float(z_hi)
        self.iterations = int(iterations)
        self.tol = float(tol)
        self.rho_max = self.rho_c + (self.r1 if z_lo <= z_c <= z_hi else
                                     max(math.sqrt(r1 ** 2 - (z_lo - z_c) ** 2), math.sqrt(r1 ** 2 - (z_hi - z_c) ** 2)))

    # g_ext and its slope at heights z
    def _g(self, z):
        zq = z.clamp(self.z_lo, self.z_hi)
        u = zq - self.z_c
        s = torch.sqrt(self.r1 * self.r1 - u * u)
        slope = -u / s
        return self.rho_c + s + slope * (z - zq), slope

    def _parts(self, o, d, t):
        """``(Sn, dSn, rho, s)`` at ``o + t d``: ``S = Sn / s`` and ``S' = dSn / (rho s)``.

        ``s = sqrt(r1^2 - u^2) > 0`` (``z`` is clamped strictly inside the arc) and ``rho > 0``
        (clamped at 1e-12 on the axis, where any subgradient will do), so ``Sn`` and ``dSn``
        have the signs of ``S`` and ``S'``, and Newton's step ``S / S' = Sn rho / dSn`` costs one
        division instead of three.
        """
        x = o[0] + t * d[0]
        y = o[1] + t * d[1]
        z = o[2] + t * d[2]
        rho = torch.sqrt(x * x + y * y).clamp_min(1e-12)
        zq = z.clamp(self.z_lo, self.z_hi)
        u = zq - self.z_c
        s = torch.sqrt(self.r1 * self.r1 - u * u)
        # S = rho - g, g = rho_c + s + slope (z - zq), slope = -u / s; S' = (x dx + y dy) / rho - slope dz.
        sn = (rho - self.rho_c - s) * s + u * (z - zq)
        dsn = (x * d[0] + y * d[1]) * s + u * d[2] * rho
        return sn, dsn, rho, s

    def value(self, p: Vec) -> torch.Tensor:
        """``S = rho - g(z)`` at points (negative inside the set, ~ signed distance near the surface)."""
        g, _ = self._g(p[2])
        return torch.sqrt(p[0] * p[0] + p[1] * p[1]) - g

    def entry(self, o: Vec, d: Vec, t_lo=None, t_hi=None) -> torch.Tensor:
        """Entry ``t`` by monotone Newton from ``t_lo`` (left end of the lens's bounding box)."""
        return self.entry_status(o, d, t_lo, t_hi)[0]

    def entry_status(self, o: Vec, d: Vec, t_lo=None, t_hi=None):
        """``(t, unconverged)``: entry ``t`` and the rays still short of the root after the iterations.

        Unconverged rays (a root ahead but ``S > tol`` after ``iterations`` steps, e.g. nearly
        tangent rays) are reported as misses and counted, never returned as NaN.
        """
        return self.entry_capped(o, d, t_lo, t_hi)[:2]

    def entry_capped(self, o: Vec, d: Vec, t_lo=None, t_hi=None, cap: int | None = None):
        """:meth:`entry_status` plus ``unfinished``. With ``cap``, at most ``cap`` steps are taken,
        on every ray (masks, no compaction: what ``torch.compile`` fuses), and ``unfinished``
        marks the rays whose next step would still move them (the caller retraces those
        without the cap); without a cap it is None.
        """
        t_lo, t_hi = self._bracket(o, d, t_lo, t_hi)
        sn, dsn, rho, s = self._parts(o, d, t_lo)
        starts_inside = sn <= 0
        t, S, dsn, dead, unfinished = self._newton(o, d, t_lo, sn, dsn, rho, s, t_lo <= t_hi, True, cap)
        ahead = ~dead & ~starts_inside & (t <= t_hi)
        hit = ahead & (S <= self.tol)
        unconverged = ahead & (S > self.tol) & (dsn < 0)
        out = torch.where(hit, t, torch.full_like(t, INF))
        return torch.where(starts_inside, torch.full_like(t, -INF), out), unconverged, unfinished

    def _newton(self, o, d, t, sn, dsn, rho, s, active, left: bool, cap: int | None = None):
        """Monotone Newton from ``t`` on the rays that need it.

        Returns ``(t, S, dSn, dead, unfinished)`` for every ray; ``dS`` has the sign of ``dSn``;
        ``dead`` marks rays whose iteration found no root on its side (``S > 0`` with the slope
        pointing away); ``unfinished`` is as in :meth:`entry_capped`.
        """
        need = active & (sn > 0)
        dead = torch.zeros_like(need)
        if cap is not None or torch.compiler.is_compiling():
            # Masks, fixed iterations: no data-dependent shapes or syncs, so the steps fuse
            # into one loop under torch.compile.
            for _ in range(self.iterations if cap is None else min(cap, self.iterations)):
                pos = need & (sn > 0)
                toward = (dsn < 0) if left else (dsn > 0)
                move = pos & toward
                dead = dead | (pos & ~toward)
                t = torch.where(move, t - sn * rho / torch.where(move, dsn, torch.ones_like(dsn)), t)
                sn, dsn, rho, s = self._parts(o, d, t)
            unfinished = None
            if cap is not None and cap < self.iterations:
                # The uncapped solve would look at this state again: a ray found dead here is
                # dead there too, one still moving (more than rounding) is unfinished.
                pos = need & (sn > 0)
                toward = (dsn < 0) if left else (dsn > 0)
                dead = dead | (pos & ~toward)
                move = pos & toward & ~dead
                step = sn * rho / torch.where(move, dsn, torch.ones_like(dsn))
                unfinished = move & (step.abs() > 1e-7 * (1.0 + t.abs()))
            elif cap is not None:
                unfinished = torch.zeros_like(need)
            return t, sn / s, dsn, dead, unfinished
        if not bool(need.any()):
            return t, sn / s, dsn, dead, None
        # Eager: most rays converge in 4-5 steps, a few near tangency take 9. So iterate the
        # rays that need it for a few steps, then only the ones still moving (compacted once).
        t, sn, dsn, s = t.clone(), sn.clone(), dsn.clone(), s.clone()
        idx = torch.nonzero(need).squeeze(1)
        oo = tuple(c[idx] for c in o)
        dd = tuple(c[idx] for c in d)
        tt, sn_, dsn_, rho_, s_ = t[idx], sn[idx], dsn[idx], rho[idx], s[idx]
        gone = torch.zeros_like(tt, dtype=torch.bool)
        first = min(4, self.iterations)
        for it in range(self.iterations):
            pos = sn_ > 0
            toward = (dsn_ < 0) if left else (dsn_ > 0)
            move = pos & toward
            gone = gone | (pos & ~toward)
            step = torch.where(move, sn_ * rho_ / torch.where(move, dsn_, torch.ones_like(dsn_)), torch.zeros_like(sn_))
            tt = tt - step
            sn_, dsn_, rho_, s_ = self._parts(oo, dd, tt)
            if it == first - 1 and it < self.iterations - 1:
                t[idx], sn[idx], dsn[idx], s[idx], dead[idx] = tt, sn_, dsn_, s_, gone
                busy = step.abs() > 1e-7 * (1.0 + tt.abs())
                if not bool(busy.any()):
                    return t, sn / s, dsn, dead, None
                idx = idx[busy]
                oo = tuple(c[busy] for c in oo)
                dd = tuple(c[busy] for c in dd)
                tt, sn_, dsn_, rho_, s_, gone = tt[busy], sn_[busy], dsn_[busy], rho_[busy], s_[busy], gone[busy]
        t[idx], sn[idx], dsn[idx], s[idx], dead[idx] = tt, sn_, dsn_, s_, gone
        return t, sn / s, dsn, dead, None

    def exit(self, o: Vec, d: Vec, t_lo=None, t_hi=None) -> torch.Tensor:
        """Exit ``t`` by monotone Newton from ``t_hi`` (right end of the bounding box)."""
        return self.exit_capped(o, d, t_lo, t_hi)[0]

    def exit_capped(self, o: Vec, d: Vec, t_lo=None, t_hi=None, start=None, cap: int | None = None):
        """``(t, unfinished)``: exit ``t`` by monotone Newton from the right, and (with ``cap``) the
        rays still moving after ``cap`` steps (see :meth:`entry_capped`).

        Newton starts from ``start`` if given, else from ``t_hi``. Any start right of the last
        root converges onto it; a start where ``S <= 0`` is inside the set, so the set is left
        no earlier than there (``+inf`` is returned, as for a ray still inside at ``t_hi``).
        The lens passes the nearer of ``t_hi`` and the other surfaces' exits: a ray that leaves
        through the top then needs no iteration at all.
        """
        t_lo, t_hi = self._bracket(o, d, t_lo, t_hi)
        t0 = t_hi if start is None else start
        sn, dsn, rho, s = self._parts(o, d, t0)
        ends_inside = sn <= 0
        t, S, dsn, dead, unfinished = self._newton(o, d, t0, sn, dsn, rho, s, t_lo <= t_hi, False, cap)
        hit = ~dead & ~ends_inside & (S <= self.tol)
        return torch.where(hit, t, torch.full_like(t, INF)), unfinished

    def _bracket(self, o, d, t_lo, t_hi):
        if t_lo is None or t_hi is None:
            # No box given: use the cylinder rho <= rho_max over the arc's own z range.
            t_lo, t_hi, _ = box_interval(o, d, self.rho_max, self.z_c - self.r1, self.z_c + self.r1)
        return t_lo, t_hi

    def contains(self, p: Vec, tol: float) -> torch.Tensor:
        return self.value(p) <= tol

    def normal(self, p: Vec) -> Vec:
        rho = torch.sqrt(p[0] * p[0] + p[1] * p[1]).clamp_min(1e-30)
        _, slope = self._g(p[2])
        nz = -slope
        inv = 1.0 / torch.sqrt(1.0 + nz * nz)
        return p[0] / rho * inv, p[1] / rho * inv, nz * inv
