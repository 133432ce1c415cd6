"""What every normal solver returns, and the one place that turns a raw solve into it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # torch is imported by the functions that use it: NormalResult alone needs none
    import torch

    from pipeline.normals import _lstsq

__all__ = ["NormalResult", "finalize", "finalize_tensors", "to_result", "concat"]


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
        Weighted RMS of ``I_k - rho n . L_k`` over the observations used, in observation units.
    condition : ndarray, shape (H, W), float
        Condition number of the (weighted) light matrix at the pixel, capped at 1e12.
    mask : ndarray, shape (H, W), bool
        True where the normal is trustworthy: at least three usable observations, a
        well-conditioned light matrix, a non-zero albedo and a normal facing the camera.
    count : ndarray, shape (H, W), int32
        Number of observations used at each pixel.
    meta : dict
        Solver name and parameters.
    confidence : ndarray, shape (H, W), float32, optional
        In [0, 1], 0 outside the mask, from solvers that rate their own answers (the
        calibration models: what it measures is in ``meta["confidence"]``); None otherwise.
    """

    normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    condition: np.ndarray
    mask: np.ndarray
    count: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    confidence: np.ndarray | None = None

    @property
    def valid_fraction(self) -> float:
        """Fraction of pixels whose normal is valid."""
        return float(self.mask.mean()) if self.mask.size else 0.0


def finalize_tensors(b: torch.Tensor, m: _lstsq.Moments, cond: torch.Tensor, *, max_condition: float = 1e3,
                     min_count: int = 3, finite_inputs: bool = False) -> dict[str, torch.Tensor]:
    """The per-pixel outputs as tensors with pixels last (see :func:`finalize`)."""
    import torch

    from pipeline.normals import _lstsq
    from pipeline.normals import _torch as T

    if not finite_inputs:
        finite = torch.isfinite(b).all(0)
        b = torch.nan_to_num(b, nan=0.0, posinf=0.0, neginf=0.0)
    n, norm = _lstsq.unit(b)
    valid = (norm > 0) & (m.count >= min_count) & (cond <= max_condition) & (n[2] > 0)
    if not finite_inputs:
        valid = valid & finite
    flat = torch.zeros((3, 1), dtype=n.dtype, device=n.device)
    flat[2] = 1.0
    n = torch.where(valid, n, flat)
    rho, p, q = _lstsq.group_albedo(m, n)
    res = _lstsq.residual_rms(m, p, q)
    zero = torch.zeros((), dtype=n.dtype, device=n.device)
    # Moments of huge but finite inputs can overflow to Inf in the products (a 1e30 observation
    # squares to Inf in float32), also when every input is finite: outputs are always cleaned.
    rho = torch.nan_to_num(rho, nan=0.0, posinf=0.0, neginf=0.0)
    res = torch.nan_to_num(res, nan=0.0, posinf=torch.finfo(res.dtype).max, neginf=0.0)  # overflowed: a huge misfit
    cond = torch.nan_to_num(cond, nan=T.COND_CAP, posinf=T.COND_CAP, neginf=T.COND_CAP)
    return {"normals": n, "albedo": torch.where(valid, rho, zero), "residual": torch.where(valid, res, zero),
            "condition": cond.expand(n.shape[1]) if cond.numel() == 1 else cond, "mask": valid,
            "count": m.count}


def to_result(t: dict[str, torch.Tensor], shape: tuple[int, int], meta: dict | None = None) -> NormalResult:
    """Tensors with pixels last -> a :class:`NormalResult` of ``(H, W, ...)`` numpy arrays."""
    import torch

    H, W = shape
    out_dtype = np.float64 if t["normals"].dtype == torch.float64 else np.float32

    def out(x):  # (..., M) -> (H, W, ...), one transposing copy made by torch
        x = x.detach()
        if x.dim() == 2:
            x = x.T.contiguous()
        return x.cpu().numpy().reshape((H, W) + tuple(x.shape[1:]))

    return NormalResult(
        normals=out(t["normals"]).astype(out_dtype, copy=False),
        albedo=out(t["albedo"]).astype(out_dtype, copy=False),
        residual=out(t["residual"]).astype(out_dtype, copy=False),
        condition=out(t["condition"]).astype(out_dtype, copy=False),
        mask=out(t["mask"]).astype(bool, copy=False),
        count=out(t["count"]).astype(np.int32, copy=False),
        meta=dict(meta or {}),
    )


def concat(parts: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Join per-chunk outputs along the pixel axis."""
    import torch

    if len(parts) == 1:
        return parts[0]
    return {k: torch.cat([p[k] for p in parts], dim=-1) for k in parts[0]}


def finalize(b: torch.Tensor, m: _lstsq.Moments, cond: torch.Tensor, shape: tuple[int, int], *,
             max_condition: float = 1e3, min_count: int = 3, meta: dict | None = None,
             finite_inputs: bool = False) -> NormalResult:
    """Turn scaled normals ``b = rho n`` ``(3, M)`` and the moments they came from into a
    :class:`NormalResult`.

    Pixels with fewer than ``min_count`` used observations, ``cond > max_condition``
    (``cond`` is ``(M,)`` or ``(1,)``), a zero or non-finite ``b`` or a normal facing away from
    the camera are masked and get the flat normal, zero albedo and zero residual.
    ``finite_inputs`` (integer observations, finite lights: nothing can overflow) skips the
    NaN/Inf scrubbing, which is a good part of the real-time path's cost.
    """
    t = finalize_tensors(b, m, cond, max_condition=max_condition, min_count=min_count, finite_inputs=finite_inputs)
    return to_result(t, shape, meta)
