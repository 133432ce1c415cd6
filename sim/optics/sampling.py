"""Ray sampling: points of the unit square, and LED emission directions from them.

Samplers (all seeded and reproducible for a given seed and chunk size):

``grid``        the paper's deterministic ``k x k`` grid of cell centres (``k = round(sqrt(n))``)
``random``      uniform random points (torch generator seeded with ``seed``)
``stratified``  one uniform random point in each cell of the ``k x k`` grid
``sobol``       scrambled Sobol points (``torch.quasirandom.SobolEngine``)

Emission: ``u`` picks the polar angle by inverting the CDF of ``cos^m theta sin theta`` on
``[0, theta_c]`` (so every ray carries the same power) and ``v`` the azimuth.
"""

from __future__ import annotations

import math

import torch

from sim.optics import instrument
from sim.optics.emitter import SAMPLERS, actual_rays, emitter_frame, profile_constants

__all__ = ["SAMPLERS", "actual_rays", "SquareSampler", "grid_points", "emission_directions"]

class SquareSampler:
    """Points of ``[0, 1)^2`` drawn chunk by chunk.

    Examples
    --------
    >>> s = SquareSampler(4, "grid", device="cpu", dtype=torch.float64)
    >>> u, v = s.draw(0, 4); u.tolist(), v.tolist()
    ([0.25, 0.25, 0.75, 0.75], [0.25, 0.75, 0.25, 0.75])
    """

    def __init__(self, n: int, kind: str, seed: int = 0, device="cpu", dtype=torch.float32):
        self.n = actual_rays(n, kind)
        self.kind = kind
        self.k = max(1, round(math.sqrt(self.n)))
        self.device = torch.device(device)
        self.dtype = dtype
        self.gen = torch.Generator(device="cpu").manual_seed(int(seed))
        self.sobol = torch.quasirandom.SobolEngine(2, scramble=True, seed=int(seed)) if kind == "sobol" else None

    def indices(self, start: int, stop: int):
        """The float64 cell indices ``start .. stop-1`` of the grid samplers."""
        return torch.arange(start, stop, device=self.device, dtype=torch.float64)

    def draw(self, start: int, stop: int):
        """Samples ``start .. stop-1`` (call with consecutive ranges for reproducibility)."""
        m = stop - start
        if self.kind in ("grid", "stratified"):
            idx = self.indices(start, stop)
            if self.kind == "grid":
                return grid_points(idx, self.k, self.dtype)
            jit = torch.rand(2, m, generator=self.gen, dtype=torch.float64).to(self.device, self.dtype)
            return grid_points(idx, self.k, self.dtype, jit[0], jit[1])
        if self.kind == "random":
            r = torch.rand(2, m, generator=self.gen, dtype=torch.float64).to(self.device, self.dtype)
            return r[0], r[1]
        r = self.sobol.draw(m, dtype=torch.float64).to(self.device, self.dtype)
        return r[:, 0].contiguous(), r[:, 1].contiguous()


def grid_points(idx, k, dtype, ju=0.5, jv=0.5):
    """Points of the ``k x k`` grid's cells ``idx`` (float64 indices, row-major): ``(u, v)``.

    ``ju, jv`` place each point in its cell (0.5: the centre). Elementwise, so the fused
    tracer computes the grid sampler's points in its compiled loop (``k`` may be a 0-d tensor).

    Examples
    --------
    >>> u, v = grid_points(torch.arange(4, dtype=torch.float64), 2, torch.float64)
    >>> u.tolist(), v.tolist()
    ([0.25, 0.25, 0.75, 0.75], [0.25, 0.75, 0.25, 0.75])
    """
    # Row/column of each sample (float64 holds indices exactly up to 2^53 and avoids slow
    # int64 division).
    i64 = torch.floor(idx / k)
    i = i64.to(dtype)
    j = (idx - i64 * k).to(dtype)
    return (i + ju) / k, (j + jv) / k


def emission_directions(u, v, m: float, cone_half_angle_deg: float, axis=(0.0, 0.0, 1.0), profile: bool = True,
                        azimuth: float = 0.0):
    """Unit directions ``(dx, dy, dz)`` of equal-power rays from a ``cos^m`` emitter.

    The emitter's local frame turns with the LED's ``azimuth`` about ``z``, so LED ``i`` of a
    ring emits exactly LED 0's rays rotated by its azimuth (what makes hit rotation exact).
    With ``profile=False`` (the emission-profile effect disabled) the LED is isotropic inside
    its cone (``m = 0``).

    Examples
    --------
    >>> import torch
    >>> d = emission_directions(torch.tensor([0.0]), torch.tensor([0.0]), 1.0, 60.0)
    >>> [round(float(c[0]), 6) for c in d]
    [0.0, 0.0, 1.0]
    """
    if profile:
        instrument.count("emission_profile")
    a, e = profile_constants(m, cone_half_angle_deg, profile)
    cos_t = torch.pow(1.0 - u * a, e)
    sin_t = torch.sqrt(torch.clamp(1.0 - cos_t * cos_t, min=0.0))
    phi = (2.0 * math.pi) * v
    lx, ly, lz = sin_t * torch.cos(phi), sin_t * torch.sin(phi), cos_t
    e1, e2, e3 = emitter_frame(axis, azimuth)
    ca, sa = math.cos(azimuth), math.sin(azimuth)
    x0 = lx * e1[0] + ly * e2[0] + lz * e3[0]
    y0 = lx * e1[1] + ly * e2[1] + lz * e3[1]
    z0 = lx * e1[2] + ly * e2[2] + lz * e3[2]
    if azimuth == 0.0:
        return x0, y0, z0
    return ca * x0 - sa * y0, sa * x0 + ca * y0, z0
