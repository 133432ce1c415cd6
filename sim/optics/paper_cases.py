"""The paper's three intersection cases (IrisTac §IV-A, eqs. 1-14), exactly as written.

Case 1 (eqs. 1-4)   the ray, the source and the axis are coplanar: a line meets the arc's
                    circle in that plane; ``AP = AC - CP`` (the near root).
Case 2 (eqs. 5-13)  the general swept-arc side: the azimuth ``theta`` of the hit solves
                    ``g(theta) = (d - EF)^2 - BH^2 = 0`` by Newton's method from ``theta_0 = 0``
                    for 20 iterations. The paper's frame has the source at ``(-r0, 0, A_z)``;
                    we rotate each ray into it and back.
Case 3 (eq. 14)     the spherical top seen from inside: ``AP = AB . i + sqrt(r^2 - |AB x i|^2)``.

Where the paper's method fails we fall back and count it, never returning NaN:

* eq. (7) ``r2 = i2 r0 / (i2 cos theta - i1 sin theta)`` is 0/0 when the ray lies in a plane
  through the axis (``i2 = 0``) or the source is on the axis (``r0 = 0``): case 1 is used;
* Newton may converge to a wrong root (the far side, the inner half of the torus, behind the
  source) or not at all: the result is checked (residual, ``r2 >= rho_c``, ahead of the
  source, entering the surface, inside the side's z range) and replaced by the robust
  intersection (:mod:`sim.optics.torus`) when the check fails.
"""

from __future__ import annotations

import math

import torch

from sim.optics.base import Vec
from sim.optics.lens import SIDE, TOP

__all__ = ["case1_arc_in_plane", "case2_newton", "case3_sphere", "side_entry", "PaperIntersector"]


def _dot(a: Vec, b: Vec):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross_norm(a: Vec, b: Vec):
    cx = a[1] * b[2] - a[2] * b[1]
    cy = a[2] * b[0] - a[0] * b[2]
    cz = a[0] * b[1] - a[1] * b[0]
    return torch.sqrt(cx * cx + cy * cy + cz * cz)


def case1_arc_in_plane(A: Vec, i: Vec, B: Vec, r: float):
    """Case 1, eqs. (1)-(4): the near intersection of a ray with a circle of centre ``B``, radius ``r``.

    Returns ``(P, n, ok)``; ``n = BP / r`` (outward), ``ok`` False where the ray misses the
    circle or the intersection lies behind ``A``.

    Examples
    --------
    >>> import torch
    >>> t = lambda *v: tuple(torch.tensor([float(x)]) for x in v)
    >>> P, n, ok = case1_arc_in_plane(t(-10, 0, 0), t(1, 0, 0), t(0, 0, 0), 2.0)
    >>> [float(c[0]) for c in P], [float(c[0]) for c in n], bool(ok[0])
    ([-2.0, 0.0, 0.0], [-1.0, 0.0, 0.0], True)
    """
    AB = (B[0] - A[0], B[1] - A[1], B[2] - A[2])
    AC = _dot(i, AB)
    d = _cross_norm(i, AB)
    ok = d <= r
    CP = torch.sqrt(torch.clamp(r * r - d * d, min=0.0))
    AP = AC - CP
    ok = ok & (AP > 0)
    P = (A[0] + AP * i[0], A[1] + AP * i[1], A[2] + AP * i[2])
    n = ((P[0] - B[0]) / r, (P[1] - B[1]) / r, (P[2] - B[2]) / r)
    return P, n, ok


def case3_sphere(A: Vec, i: Vec, B: Vec, r: float):
    """Case 3, eq. (14): where a ray from inside a sphere (centre ``B``, radius ``r``) leaves it.

    Returns ``(P, n, ok)`` with ``n = BP / r``.

    Examples
    --------
    >>> import torch
    >>> t = lambda *v: tuple(torch.tensor([float(x)]) for x in v)
    >>> P, n, ok = case3_sphere(t(0, 0, 0), t(0, 0, 1), t(0, 0, -1), 3.0)
    >>> [float(c[0]) for c in P], bool(ok[0])
    ([0.0, 0.0, 2.0], True)
    """
    AB = (B[0] - A[0], B[1] - A[1], B[2] - A[2])
    c = _cross_norm(AB, i)
    disc = r * r - c * c
    ok = disc >= 0
    AP = _dot(AB, i) + torch.sqrt(torch.clamp(disc, min=0.0))
    ok = ok & (AP >= 0)
    P = (A[0] + AP * i[0], A[1] + AP * i[1], A[2] + AP * i[2])
    n = ((P[0] - B[0]) / r, (P[1] - B[1]) / r, (P[2] - B[2]) / r)
    return P, n, ok


def case2_newton(A: Vec, i: Vec, r1: float, rho_c: float, z_c: float, iterations: int = 20, theta0: float = 0.0,
                 eps: float = 1e-9):
    """Case 2, eqs. (5)-(13): the swept-arc side by Newton's method on ``g(theta)``.

    Parameters
    ----------
    A, i : (x, y, z) of (N,) tensors
        Ray origins (the source) and unit directions, optical frame.
    r1, rho_c, z_c : float
        Arc radius and centre (``GH = rho_c`` in the paper) in the meridian plane.
    iterations, theta0 :
        The paper uses 20 iterations from ``theta_0 = 0``.

    Returns
    -------
    P, n : (x, y, z) tuples
        Intersection and unit normal ``BP / |BP|`` (garbage where ``ok`` is False; finite).
    info : dict of (N,) tensors
        ``theta``, ``residual`` (``|g|`` at the end), ``singular`` (eq. 7 is 0/0: the ray in a
        plane through the axis, or the source on the axis), ``ok`` (finite, converged,
        non-singular, ``r2 > 0`` and ahead of the source).
    """
    phiA = torch.atan2(A[1], A[0])
    r0 = torch.sqrt(A[0] * A[0] + A[1] * A[1])
    # Rotate by (pi - phiA) about z so that A sits at (-r0, 0, A_z), the paper's frame.
    c, s = torch.cos(math.pi - phiA), torch.sin(math.pi - phiA)
    i1 = c * i[0] - s * i[1]
    i2 = s * i[0] + c * i[1]
    i3 = i[2]
    h = torch.sqrt(i1 * i1 + i2 * i2)
    singular = (h.abs() < eps) | (i2.abs() <= eps * h.clamp_min(eps)) | (r0 < eps)
    one = torch.ones_like(i1)
    i2s = torch.where(singular, one, i2)
    d = z_c - A[2]
    theta = torch.full_like(i1, theta0)

    def g_and_dg(th):
        ct, st = torch.cos(th), torch.sin(th)
        den = i2s * ct - i1 * st
        den = torch.where(den.abs() < 1e-30, torch.full_like(den, 1e-30), den)
        r2 = i2s * r0 / den                                   # eq. (7)
        dr2 = i2s * r0 * (i2s * st + i1 * ct) / (den * den)
        den2 = i1 * ct + i2s * st
        den2 = torch.where(den2.abs() < 1e-30, torch.full_like(den2, 1e-30), den2)
        num = r0 * ct - r2                                    # eq. (9): FP
        lam = num / den2
        dlam = ((-r0 * st - dr2) * den2 - num * (-i1 * st + i2s * ct)) / (den2 * den2)
        EF = i3 * lam                                         # eq. (10)
        u = d - EF
        g = u * u - (r1 * r1 - (r2 - rho_c) ** 2)             # eq. (12) with eq. (11) squared
        dg = -2.0 * u * i3 * dlam + 2.0 * (r2 - rho_c) * dr2
        return g, dg, r2, EF, lam

    for _ in range(iterations):
        g, dg, *_ = g_and_dg(theta)
        step = g / torch.where(dg.abs() < 1e-30, torch.full_like(dg, 1e-30), dg)
        # A diverging iterate (non-finite) stops where it is: the check below rejects it.
        theta = torch.where(torch.isfinite(step), theta - step, theta)
    g, _, r2, EF, lam = g_and_dg(theta)
    ct, st = torch.cos(theta), torch.sin(theta)
    Px, Py, Pz = -ct * r2, -st * r2, A[2] + EF                # eq. (13)
    Bx, By = -ct * rho_c, -st * rho_c
    nx, ny, nz = Px - Bx, Py - By, Pz - z_c
    nn = torch.sqrt(nx * nx + ny * ny + nz * nz).clamp_min(1e-30)
    # Back to the optical frame.
    P = (c * Px + s * Py, -s * Px + c * Py, Pz)
    n = ((c * nx + s * ny) / nn, (-s * nx + c * ny) / nn, nz / nn)
    scale = r1 * max(r1, abs(rho_c), 1.0)
    residual = g.abs()
    ok = ~singular & torch.isfinite(residual) & (residual <= 1e-4 * scale) & (r2 > 0) & (lam > 0)
    fin = lambda v: tuple(torch.where(torch.isfinite(x), x, torch.zeros_like(x)) for x in v)  # noqa: E731
    return fin(P), fin(n), {"theta": theta, "residual": torch.where(torch.isfinite(residual), residual,
                                                                       torch.full_like(residual, math.inf)),
                            "singular": singular, "ok": ok}


def side_entry(o: Vec, d: Vec, lens, iterations: int = 20):
    """The paper's side entry with its checks: ``(P, n, ok, singular)``.

    Case 2 by Newton; where eq. (7) is singular, case 1 in the plane of the source and the
    axis (the arc centre on the source's side). ``ok`` requires the method's own success
    (converged, ahead of the source) and a genuine entry: on the outer half of the arc
    (``rho >= rho_c``), within the side's z range, against the outward normal. Newton
    iterates that converge to a wrong root (the far side, the inner half of the torus) fail
    these checks.
    """
    ln = lens
    P2, n2, info = case2_newton(o, d, ln.arc_radius, ln.centre_rho, ln.centre_z, iterations)
    phi = torch.atan2(o[1], o[0])
    B = (ln.centre_rho * torch.cos(phi), ln.centre_rho * torch.sin(phi), torch.full_like(phi, ln.centre_z))
    P1, n1, ok1 = case1_arc_in_plane(o, d, B, ln.arc_radius)
    sing = info["singular"]
    P = tuple(torch.where(sing, a, b) for a, b in zip(P1, P2))
    nn = tuple(torch.where(sing, a, b) for a, b in zip(n1, n2))
    ok = torch.where(sing, ok1, info["ok"])
    rho = torch.sqrt(P[0] * P[0] + P[1] * P[1])
    entering = (d[0] * nn[0] + d[1] * nn[1] + d[2] * nn[2]) < 0
    ok = ok & entering & (rho >= ln.centre_rho) & (P[2] >= ln.bottom_z - 1e-6) & (P[2] <= ln.rim_z + 1e-6)
    return P, nn, ok, sing


class PaperIntersector:
    """The paper's method inside the tracer: replaces the robust side entry and top exit.

    The robust body decides which surface a ray meets (the paper's method has no notion of
    it); for side entries the point and normal then come from case 2 (case 1 where eq. 7 is
    singular) and for top exits from case 3. Results that fail the checks fall back to the
    robust ones and are counted in :attr:`counters`.
    """

    def __init__(self, lens, iterations: int = 20):
        self.lens = lens
        self.iterations = int(iterations)
        self.counters = {"paper_case1": 0, "paper_case2": 0, "paper_case3": 0, "paper_fallbacks": 0}

    def entry(self, o: Vec, d: Vec, p: Vec, n: Vec, sid, hit):
        ln = self.lens
        if not ln.is_arc:
            return p, n
        m = hit & (sid == SIDE)
        if not bool(m.any()):
            return p, n
        P, nn, ok, sing = side_entry(o, d, ln, self.iterations)
        use = m & ok
        self.counters["paper_case1"] += int((use & sing).sum())
        self.counters["paper_case2"] += int((use & ~sing).sum())
        self.counters["paper_fallbacks"] += int((m & ~ok).sum())
        return (tuple(torch.where(use, a, b) for a, b in zip(P, p)),
                tuple(torch.where(use, a, b) for a, b in zip(nn, n)))

    def exit(self, o: Vec, d: Vec, q: Vec, n: Vec, sid, mask):
        ln = self.lens
        m = mask & (sid == TOP)
        if ln.top_conic != 0.0 or not bool(m.any()):
            # Case 3 is the paper's sphere; a conic top keeps the robust exit (closed form too).
            return q, n
        B = (torch.zeros_like(o[0]), torch.zeros_like(o[0]), torch.full_like(o[0], ln.apex_z - ln.top_radius))
        P, nn, ok = case3_sphere(o, d, B, ln.top_radius)
        use = m & ok
        self.counters["paper_case3"] += int(use.sum())
        self.counters["paper_fallbacks"] += int((m & ~ok).sum())
        return (tuple(torch.where(use, a, b) for a, b in zip(P, q)),
                tuple(torch.where(use, a, b) for a, b in zip(nn, n)))
