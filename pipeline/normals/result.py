"""What every normal solver returns, and the one place that turns a raw solve into it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from pipeline.normals import _torch as T

__all__ = ["NormalResult", "finalize"]


@dataclass
class NormalResult:
    """Per-pixel output of a normal solver. Every array is finite.

    Attributes
    ----------
    normals : ndarray, shape (H, W, 3), float
        Unit normals in the reconstruction frame (+z toward the camera). Invalid pixels hold
        the flat-gel normal ``(0, 0, 1)``.
    albedo : ndarray, shape (H, W, G), float
        Least-squares albedo per albedo group (``G`` = camera channels when the solver was
        given ``groups``, else 1), in units of observation / light. 0 at invalid pixels.
    residual : ndarray, shape (H, W), float
        RMS of ``I_k - rho n . L_k`` over the observations used, in observation units.
    condition : ndarray, shape (H, W), float
        Condition number of the (weighted) light matrix at the pixel, capped at 1e12.
    mask : ndarray, shape (H, W), bool
        True where the normal is trustworthy: at least three usable observations, a
        well-conditioned light matrix, a non-zero albedo and a normal facing the camera.
    count : ndarray, shape (H, W), int32
        Number of observations used at each pixel.
    meta : dict
        Solver name and parameters.
    """

    normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    condition: np.ndarray
    mask: np.ndarray
    count: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def valid_fraction(self) -> float:
        """Fraction of pixels whose normal is valid."""
        return float(self.mask.mean()) if self.mask.size else 0.0


def finalize(b: torch.Tensor, I: torch.Tensor, L: torch.Tensor, w: torch.Tensor, cond: torch.Tensor,
             shape: tuple[int, int], *, groups: torch.Tensor | None = None, num_groups: int = 1,
             max_condition: float = 1e3, min_count: int = 3, meta: dict | None = None) -> NormalResult:
    """Turn scaled normals ``b = rho n`` ``(M, 3)`` into a :class:`NormalResult`.

    ``I`` ``(N, M)`` observations, ``L`` ``(N, 3)`` or ``(N, M, 3)`` lights, ``w`` ``(N, M)``
    the weights actually used, ``cond`` ``(M,)`` condition numbers. Pixels with fewer than
    ``min_count`` used observations, ``cond > max_condition``, a zero or non-finite ``b`` or a
    normal facing away from the camera are masked and get the flat normal.
    """
    H, W = shape
    out_dtype = np.float64 if b.dtype == torch.float64 else np.float32
    norm = torch.linalg.vector_norm(b, dim=-1)
    count = (w > 0).sum(0)
    finite_b = torch.isfinite(b).all(-1) & torch.isfinite(norm)
    ok_norm = finite_b & (norm > 0)
    safe = torch.where(ok_norm, norm, torch.ones_like(norm))
    n = torch.where(ok_norm[:, None], b / safe[:, None], torch.zeros_like(b))
    valid = ok_norm & (count >= min_count) & (cond <= max_condition) & (n[:, 2] > 0)
    flat = torch.zeros_like(n)
    flat[:, 2] = 1.0
    n = torch.where(valid[:, None], n, flat)
    if groups is None:
        groups = torch.zeros(I.shape[0], dtype=torch.long, device=I.device)
        num_groups = 1
    s = T.project(L, n)
    rho = T.group_albedo(I, s, w, groups, num_groups)
    pred = rho.T[groups] * s
    res = T.weighted_rms(I - pred, w)
    rho = torch.where(valid[:, None], rho, torch.zeros_like(rho))
    res = torch.where(valid & torch.isfinite(res), res, torch.zeros_like(res))
    cond = torch.where(torch.isfinite(cond), cond, torch.full_like(cond, T.COND_CAP))

    def out(x, *tail):
        return x.detach().cpu().numpy().reshape(H, W, *tail)

    return NormalResult(
        normals=out(n, 3).astype(out_dtype, copy=False),
        albedo=out(rho, num_groups).astype(out_dtype, copy=False),
        residual=out(res).astype(out_dtype, copy=False),
        condition=out(cond).astype(out_dtype, copy=False),
        mask=out(valid).astype(bool, copy=False),
        count=out(count).astype(np.int32, copy=False),
        meta=dict(meta or {}),
    )
