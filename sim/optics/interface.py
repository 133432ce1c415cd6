"""What happens at a refracting interface: vector Snell's law, total internal reflection, Fresnel.

All functions take structure-of-arrays vectors ``(x, y, z)`` of 1-D torch tensors.
"""

from __future__ import annotations

import torch

from sim.optics import instrument
from sim.optics.base import Vec

__all__ = ["refract", "reflect", "fresnel_transmittance"]


def refract(d: Vec, n: Vec, eta):
    """Refract unit directions ``d`` at unit normals ``n`` (on the incident side, ``n . d < 0``).

    ``eta = n1 / n2`` (scalar or (N,) tensor). Returns ``(t, cos_i, cos_t, tir)``: the refracted
    unit direction (vector Snell's law, ``t = eta d + (eta cos_i - cos_t) n``), the cosines of
    the incidence and refraction angles, and the total-internal-reflection mask (where ``t``
    is meaningless and ``cos_t = 0``).

    Examples
    --------
    Normal incidence goes straight through; 60 degrees from glass (1.5) to air is TIR:

    >>> import torch, math
    >>> one = lambda v: torch.tensor([v])
    >>> t, ci, ct, tir = refract((one(0.0), one(0.0), one(1.0)), (one(0.0), one(0.0), one(-1.0)), 1 / 1.5)
    >>> [round(float(c[0]), 6) for c in t], bool(tir[0])
    ([0.0, 0.0, 1.0], False)
    >>> s = math.sin(math.radians(60)); c = math.cos(math.radians(60))
    >>> bool(refract((one(s), one(0.0), one(c)), (one(0.0), one(0.0), one(-1.0)), 1.5)[3][0])
    True
    """
    cos_i = -(d[0] * n[0] + d[1] * n[1] + d[2] * n[2])
    sin2_t = eta * eta * torch.clamp(1.0 - cos_i * cos_i, min=0.0)
    tir = sin2_t > 1.0
    cos_t = torch.sqrt(torch.clamp(1.0 - sin2_t, min=0.0))
    k = eta * cos_i - cos_t
    t = (eta * d[0] + k * n[0], eta * d[1] + k * n[1], eta * d[2] + k * n[2])
    return t, cos_i, cos_t, tir


def reflect(d: Vec, n: Vec) -> Vec:
    """Mirror unit directions ``d`` about unit normals ``n``: ``d - 2 (d . n) n``.

    Examples
    --------
    >>> import torch
    >>> one = lambda v: torch.tensor([v], dtype=torch.float64)
    >>> [float(c[0]) for c in reflect((one(0.6), one(0.0), one(0.8)), (one(0.0), one(0.0), one(-1.0)))]
    [0.6, 0.0, -0.8]
    """
    k = 2.0 * (d[0] * n[0] + d[1] * n[1] + d[2] * n[2])
    return d[0] - k * n[0], d[1] - k * n[1], d[2] - k * n[2]


def fresnel_transmittance(cos_i, cos_t, n1, n2):
    """Unpolarized Fresnel power transmittance ``T = 1 - (R_s + R_p) / 2``.

    ``R = 1 - T`` is the reflected fraction, so ``T + R = 1`` to rounding (energy bookkeeping).
    Where ``cos_t = 0`` (TIR or grazing) ``T = 0``.

    Examples
    --------
    Normal incidence on glass of index 1.5 reflects ``((1.5 - 1) / (1.5 + 1))^2 = 4 %``:

    >>> import torch
    >>> round(float(fresnel_transmittance(torch.ones(1), torch.ones(1), 1.0, 1.5)[0]), 6)
    0.96
    """
    instrument.count("fresnel")  # under torch.compile, the tracer counts at its call site
    a = n1 * cos_i
    b = n2 * cos_t
    c = n2 * cos_i
    e = n1 * cos_t
    den_s = a + b
    den_p = c + e
    ok = (den_s > 0) & (den_p > 0)
    rs = (a - b) / torch.where(ok, den_s, torch.ones_like(den_s))
    rp = (c - e) / torch.where(ok, den_p, torch.ones_like(den_p))
    T = 1.0 - 0.5 * (rs * rs + rp * rp)
    return torch.where(ok & (cos_t > 0), T.clamp(0.0, 1.0), torch.zeros_like(T))
