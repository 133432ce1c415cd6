"""The LED as an emitter, without torch: sampler names, ray counts, the ``cos^m`` profile and the LED frame.

Shared by the torch reference (:mod:`sim.optics.sampling`) and the compiled kernel
(:mod:`sim.optics.engine`), so that both emit the same rays from the same square samples.
"""

from __future__ import annotations

import math

__all__ = ["SAMPLERS", "actual_rays", "profile_constants", "emitter_frame"]

SAMPLERS = ("grid", "random", "stratified", "sobol")


def actual_rays(n: int, sampler: str) -> int:
    """Number of rays a sampler really draws for a request of ``n`` (grids round to ``k^2``).

    Examples
    --------
    >>> actual_rays(1_000_000, "grid"), actual_rays(1000, "grid"), actual_rays(1000, "sobol")
    (1000000, 1024, 1000)
    """
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; expected one of {SAMPLERS}")
    if sampler in ("grid", "stratified"):
        k = max(1, round(math.sqrt(n)))
        return k * k
    return int(n)


def profile_constants(m: float, cone_half_angle_deg: float, profile: bool = True) -> tuple[float, float]:
    """``(a, e)`` of the equal-power polar angle: ``cos theta = (1 - u a)^e`` for a square sample ``u``.

    Inverting the CDF of ``cos^m theta sin theta`` on ``[0, theta_c]``: ``a = 1 - cos(theta_c)^(m+1)``
    and ``e = 1 / (m + 1)``. With ``profile=False`` (the emission-profile effect disabled) the LED
    is isotropic inside its cone (``m = 0``).

    Examples
    --------
    >>> [round(x, 6) for x in profile_constants(1.0, 60.0)]
    [0.75, 0.5]
    """
    mp = float(m) if profile else 0.0
    c = math.cos(math.radians(cone_half_angle_deg))
    return 1.0 - c ** (mp + 1.0), 1.0 / (mp + 1.0)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _unit(a):
    n = math.sqrt(sum(x * x for x in a))
    return tuple(x / n for x in a)


def emitter_frame(axis, azimuth: float = 0.0):
    """Unit vectors ``(e1, e2, e3)`` of the LED's local frame in LED 0's frame (``e3`` the LED axis).

    The frame turns with the LED's ``azimuth`` about ``z``: the axis is rotated back by it, the
    frame built there and the directions rotated forward again, so LED ``i`` of a ring emits
    exactly LED 0's rays rotated by its azimuth (what makes hit rotation exact).

    Examples
    --------
    >>> emitter_frame((0.0, 0.0, 1.0))
    ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    """
    ca, sa = math.cos(azimuth), math.sin(azimuth)
    ax = _unit([float(x) for x in axis])
    a0 = (ca * ax[0] + sa * ax[1], -sa * ax[0] + ca * ax[1], ax[2])
    if abs(a0[2] - 1.0) < 1e-15:
        return (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    if abs(a0[1]) < 1e-12:
        # Tilted in the radial plane (a ring tilted toward its axis): e2 = y, e1 = y x a0.
        return (a0[2], 0.0, -a0[0]), (0.0, 1.0, 0.0), a0
    h = (0.0, 0.0, 1.0) if abs(a0[2]) < 0.9 else (1.0, 0.0, 0.0)
    e1 = _unit(_cross(h, a0))
    return e1, _cross(a0, e1), a0
