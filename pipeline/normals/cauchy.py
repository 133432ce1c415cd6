"""Robust photometric stereo (``--solver cauchy``): drop dark (shadowed) and saturated observations per pixel,
then a trimmed or iteratively reweighted least-squares solve.

Least squares assumes ``I_k = rho n . L_k`` for every observation; a cast or attached shadow
(``I_k`` near the dark level) or a clipped highlight breaks that and drags the normal. Here
each pixel keeps its own set of usable observations, so its light matrix differs from its
neighbours' and the solve is the general per-pixel one (no shared pseudo-inverse).
"""

from __future__ import annotations

import math

import numpy as np  # noqa: F401 - the examples (doctests) use it
import torch

from pipeline.normals import _inputs, _lstsq, _xp
from pipeline.normals._linalg3 import inverse3, project
from pipeline.normals._lstsq import finalize
from pipeline.normals.masking import solves_in_mask
from pipeline.normals.result import NormalResult

__all__ = ["solve_cauchy", "usable_observations"]

_METHODS = ("irls", "trim")
# Cauchy weight constant: 95% efficiency under Gaussian noise.
_CAUCHY_C = 2.385


def usable_observations(I: torch.Tensor, dark_threshold: float, saturation: float) -> torch.Tensor:
    """Boolean ``(N, M)``: finite and strictly between the dark threshold and saturation."""
    return torch.isfinite(I) & (I > dark_threshold) & (I < saturation)


def _trim(I: torch.Tensor, usable: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """Keep, per pixel, the usable observations between the ``low`` and ``1 - high`` intensity
    quantiles, never fewer than three."""
    big = torch.finfo(I.dtype).max
    key = torch.where(usable, I, torch.full_like(I, big))  # unusable sort last
    rank = torch.argsort(torch.argsort(key, dim=0), dim=0)
    n_u = usable.sum(0)
    lo = torch.floor(n_u * low).long()
    hi = torch.floor(n_u * high).long()
    # Give observations back (high end first) until at least three remain.
    excess = torch.clamp(3 - (n_u - lo - hi), min=0)
    give_hi = torch.minimum(excess, hi)
    hi = hi - give_hi
    lo = torch.clamp(lo - (excess - give_hi), min=0)
    return usable & (rank >= lo) & (rank < n_u - hi)


@solves_in_mask
def solve_cauchy(observations, lights, *, dark_threshold: float = 0.0, saturation: float = math.inf,
                 method: str = "irls", iterations: int = 5, trim_low: float = 0.25, trim_high: float = 0.1,
                 noise_floor: float | None = None, groups=None, max_condition: float = 1e3, device="cpu",
                 dtype="float32") -> NormalResult:
    """Robust normals of one observation stack.

    Parameters
    ----------
    observations : ndarray, shape (N_obs, H, W)
        Dark-subtracted intensities.
    lights : ndarray, shape (N_obs, 3) or (N_obs, H, W, 3)
        Far-field or per-pixel light vectors.
    dark_threshold : float
        Observations ``<= dark_threshold`` count as shadowed and are excluded.
    saturation : float
        Observations ``>= saturation`` count as clipped and are excluded (e.g. ``255 - dark``).
    method : {"irls", "trim"}
        ``"irls"``: start from the trimmed solve, then ``iterations`` Cauchy-reweighted
        solves over all usable observations with a per-pixel MAD scale. ``"trim"``: drop the darkest ``trim_low`` and
        brightest ``trim_high`` fraction of the usable observations, then least squares.
    noise_floor : float, optional
        Lower bound of the IRLS residual scale (default ``1e-3`` of the pixel's RMS intensity):
        stops exact data from giving infinite weights.
    groups, max_condition, device, dtype
        As in :class:`pipeline.normals.FarFieldSolver`.
    mask : ndarray, shape (H, W), optional
        Solve only these pixels (:mod:`pipeline.normals.masking`); the others come back invalid.

    Returns
    -------
    NormalResult
        ``count`` is the number of usable observations; pixels with fewer than three are masked.

    Examples
    --------
    Five lights, one observation saturated: plain least squares is pulled, robust is exact.

    >>> L = np.array([[0, 0, 1.0], [0.7, 0, 1], [0, 0.7, 1], [-0.7, 0, 1], [0, -0.7, 1]])
    >>> n = np.array([0.0, 0.0, 1.0])
    >>> I = (L @ n * 100)[:, None, None].copy(); I[1] = 255.0
    >>> res = solve_cauchy(I, L, saturation=250.0, dtype="float64")
    >>> (np.round(res.normals[0, 0], 6) + 0.0).tolist(), int(res.count[0, 0])
    ([0.0, 0.0, 1.0], 4)
    """
    if method not in _METHODS:
        raise ValueError(f"solve_cauchy: method must be one of {_METHODS}, got {method!r}")
    N, H, W, dev, dt, g, num_groups = _inputs.check_stack(observations, lights, groups, device, dtype, "solve_cauchy")
    selectors = _lstsq.group_selectors(g, num_groups, N)
    # Per-pixel weights differ between channels here, so a joint albedo would be biased even
    # under white patterns: refine for per-group albedo (see _lstsq.solve).
    iters_albedo = 2 if _inputs.group_counts_ok(g, num_groups) else 0
    raw = _xp.asarray(observations, dt, dev).reshape(N, -1)
    L, light_ok = _inputs.flatten_lights(lights, dt, dev)
    light_ok = light_ok[:, None].expand(N, H * W) if L.dim() == 2 else light_ok
    usable = usable_observations(raw, dark_threshold, saturation) & light_ok
    I = torch.where(torch.isfinite(raw), raw, torch.zeros((), dtype=dt, device=dev))
    # Start from the trimmed solve (darkest and brightest usable observations dropped): a
    # least-squares start pulled by many outliers can make the reweighting converge to them.
    trimmed = _trim(I, usable, trim_low, trim_high)
    if method == "trim":
        usable = trimmed
    w = trimmed.to(dt)
    m = _lstsq.moments(I, L, w, selectors)
    # Conditioning is judged on the usable set (IRLS weights only down-weight within it).
    cond = _lstsq.condition(L, usable.to(dt))
    inv, _ = inverse3(m.Q.sum(0))
    b = _lstsq.solve(m, inv, iters_albedo)
    w = usable.to(dt)
    if method == "irls" and iterations > 0:
        rms = torch.sqrt((w * I * I).sum(0) / torch.clamp(w.sum(0), min=1.0))
        floor = rms * 1e-3 if noise_floor is None else torch.full_like(rms, float(noise_floor))
        floor = torch.clamp(floor, min=torch.finfo(dt).tiny)
        nan = torch.full((), float("nan"), dtype=dt, device=dev)
        gid = torch.zeros(N, dtype=torch.long, device=dev) if g is None else g
        for _ in range(iterations):
            # Residuals of the full model, albedo per group: with one joint albedo a coloured
            # gel would leave channel-dependent residuals that inflate the scale estimate.
            n, _ = _lstsq.unit(b)
            rho, _, _ = _lstsq.group_albedo(m, n)
            r = I - rho[gid] * project(L, n)
            sigma = 1.4826 * torch.nanmedian(torch.where(usable, r.abs(), nan), dim=0).values
            sigma = torch.maximum(torch.where(torch.isfinite(sigma), sigma, floor), floor)
            w = usable.to(dt) / (1.0 + (r / (_CAUCHY_C * sigma)) ** 2)
            m = _lstsq.moments(I, L, w, selectors)
            inv, _ = inverse3(m.Q.sum(0))
            b = _lstsq.solve(m, inv, iters_albedo)
    return finalize(b, m, cond, (H, W), max_condition=max_condition,
                    meta={"solver": "robust", "method": method, "dark_threshold": float(dark_threshold),
                          "saturation": float(saturation), "iterations": int(iterations),
                          "max_condition": float(max_condition)})
