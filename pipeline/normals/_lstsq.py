"""Least squares for ``b = rho n`` from per-group moments, with per-group albedo by alternation.

Every least-squares solver reduces a pixel's observations to moments per albedo group ``g``
(the camera channel): ``Q_g = sum w L L^T`` (3x3), ``r_g = sum w I L`` (3), ``S_g = sum w I^2``.
From them, without touching the observations again:

- the solve: ``b = (sum_g Q_g)^-1 sum_g s_g r_g`` (``s_g = 1`` for one albedo);
- per-group albedo given the normal: ``rho_g = (n . r_g) / (n^T Q_g n)``;
- the residual: ``sum w (I - rho_g n . L)^2 = sum_g S_g - (n . r_g)^2 / (n^T Q_g n)``.

With an albedo per camera channel the model ``I_k = rho_g(k) n . L_k`` is bilinear; we
alternate: solve ``b`` jointly, estimate each group's albedo, scale each group's lights by its
relative albedo and solve again (see :func:`solve`).

Layout: pixels last. Observations ``(N, M)``, lights ``(N, 3)`` (shared) or ``(N, 3, M)``.

:func:`finalize` is the one place that turns a raw solve into a
:class:`~pipeline.normals.result.NormalResult`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.normals import _torch as T
from pipeline.normals._inputs import group_counts_ok
from pipeline.normals.result import COND_CAP, NormalResult


@dataclass
class Moments:
    """Per-group normal-equation moments of every pixel.

    Q : (G, 3, 3, M) or (G, 3, 3, 1) when the same for every pixel
    r : (G, 3, M)
    S : (G, M)
    wsum : (M,) total weight; count : (M,) observations with non-zero weight
    """

    Q: torch.Tensor
    r: torch.Tensor
    S: torch.Tensor
    wsum: torch.Tensor
    count: torch.Tensor


def group_selectors(groups: torch.Tensor | None, num_groups: int, n: int) -> list:
    """One selector per albedo group: a slice when the group's observations are evenly spaced
    (the usual pattern-major, channel-minor order: no copy), else an index tensor."""
    if groups is None:
        return [slice(None)]
    out = []
    for g in range(num_groups):
        idx = torch.nonzero(groups == g).flatten()
        if idx.numel() == 0:
            out.append(idx)
            continue
        step = int(idx[1] - idx[0]) if idx.numel() > 1 else 1
        start = int(idx[0])
        if step > 0 and torch.equal(idx, torch.arange(start, start + step * idx.numel(), step, device=idx.device)):
            out.append(slice(start, start + step * (idx.numel() - 1) + 1, step))
        else:
            out.append(idx)
    return out


def channels_share_lights(L: torch.Tensor, selectors: list, rtol: float = 1e-4) -> bool:
    """True when every group's lights are one scalar multiple of the first group's.

    Then a joint solve is exact whatever the per-group albedo (white patterns: the channels
    of a pattern see the same light), and the per-group alternation can be skipped.
    ``L`` is ``(N, 3)`` or ``(N, 3, M)``; groups of different sizes never share.
    """
    if len(selectors) < 2:
        return True
    ref = L[selectors[0]].to(torch.float64)
    ref_norm = float((ref * ref).sum())
    for sel in selectors[1:]:
        Lg = L[sel].to(torch.float64)
        if Lg.shape != ref.shape:
            return False
        a = float((Lg * ref).sum()) / max(ref_norm, 1e-300)
        if float(((Lg - a * ref) ** 2).sum()) > (rtol ** 2) * max(float((Lg * Lg).sum()), 1e-300):
            return False
    return True


def gram_shared(L: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
    """``sum_k w_k L_k L_k^T`` for shared lights ``(N, 3)``: ``(3, 3, 1)`` or ``(3, 3, M)``."""
    outer = (L[:, :, None] * L[:, None, :]).reshape(L.shape[0], 9)
    if w is None:
        return outer.sum(0).reshape(3, 3, 1)
    return (outer.T @ w).reshape(3, 3, -1)


def gram_pixel(L: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
    """``sum_k w_k L_k L_k^T`` for per-pixel lights ``(N, 3, M)``: ``(3, 3, M)``."""
    wl = L if w is None else L * w[:, None, :]
    rows = [torch.stack([(wl[:, i] * L[:, j]).sum(0) for j in range(3)]) for i in range(3)]
    return torch.stack(rows)


def condition(L: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
    """Condition number ``(M,)`` (or ``(1,)``) of the weighted light matrix, computed in float64.

    Float32 rounding alone puts the smallest eigenvalue of a rank-deficient Gram matrix near
    ``1e-7`` of the largest, i.e. a condition number of only a few thousand: too close to the
    masking threshold to tell "rank-deficient" from "merely oblique" reliably.
    """
    L64 = L.to(torch.float64)
    w64 = None if w is None else w.to(torch.float64)
    A = gram_shared(L64, w64) if L.dim() == 2 else gram_pixel(L64, w64)
    return T.condition_from_gram(A).to(L.dtype)


def moments(I: torch.Tensor, L: torch.Tensor, w: torch.Tensor | None, selectors: list,
            Q: torch.Tensor | None = None, count: torch.Tensor | None = None) -> Moments:
    """Moments of observations ``I`` ``(N, M)`` with weights ``w`` ``(N, M)`` (None: all 1).

    ``Q`` ``(G, 3, 3, M|1)`` may be passed when it is known (it does not depend on ``I``), and
    ``count`` ``(M,)`` (observations with non-zero weight) when the caller has it: a boolean
    reduction over ``(N, M)`` is slow on the CPU.
    """
    Qs, rs, Ss = [], [], []
    for sel in selectors:
        Ig, Lg = I[sel], L[sel]
        wg = None if w is None else w[sel]
        wI = Ig if wg is None else wg * Ig
        Ss.append((wI * Ig).sum(0))
        if Lg.dim() == 2:
            rs.append(Lg.T @ wI)
            if Q is None:
                Qs.append(gram_shared(Lg, wg))
        else:
            rs.append((Lg * wI[:, None, :]).sum(0))
            if Q is None:
                Qs.append(gram_pixel(Lg, wg))
    if Q is None:
        width = max(q.shape[-1] for q in Qs)
        Q = torch.stack([q.expand(3, 3, width) for q in Qs])
    M = I.shape[1]
    if w is None:
        wsum = torch.full((M,), float(I.shape[0]), dtype=I.dtype, device=I.device)
        count = torch.full((M,), I.shape[0], dtype=torch.int32, device=I.device)
    else:
        wsum = w.sum(0)
        count = (w > 0).sum(0, dtype=torch.int32) if count is None else count.to(torch.int32)
    return Moments(Q=Q, r=torch.stack(rs), S=torch.stack(Ss), wsum=wsum, count=count)


def quad(Q: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """``n^T Q_g n`` per group and pixel: ``(G, M)``."""
    nn = (n[:, None] * n[None]).reshape(9, -1)
    if Q.shape[-1] == 1:  # the same Q at every pixel: one (G, 9) @ (9, M) product
        return Q.reshape(Q.shape[0], 9) @ nn
    return (Q.reshape(Q.shape[0], 9, -1) * nn[None]).sum(1)


def unit(b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(b / |b|, |b|)`` for ``(3, M)``; zero vectors stay zero."""
    norm = torch.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    return b / torch.clamp(norm, min=torch.finfo(b.dtype).tiny), norm


def group_albedo(m: Moments, n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(rho, p, q)``: albedo ``(G, M)`` given the normal, with ``p = n . r_g``, ``q = n^T Q_g n``.

    ``q = sum w s^2 >= 0``, and ``q = 0`` forces ``p = sum w I s = 0``, so a clamped division
    gives albedo 0 there without a branch.
    """
    p = m.r[:, 0] * n[0] + m.r[:, 1] * n[1] + m.r[:, 2] * n[2]
    q = quad(m.Q, n)
    return p / torch.clamp(q, min=torch.finfo(q.dtype).tiny), p, q


def solve(m: Moments, inv: torch.Tensor, iterations: int = 0) -> torch.Tensor:
    """``b`` ``(3, M)`` from moments and the inverse ``(3, 3, M|1)`` of ``sum_g Q_g``; then
    ``iterations`` per-group albedo alternation steps (only meaningful with several groups).

    The alternation rescales the *model*, not the data: with relative albedo ``s_g`` the
    system becomes ``(sum_g s_g^2 Q_g) b = sum_g s_g r_g``, so noisy dim channels are not
    amplified. When every group sees the same lights (white patterns) the joint solve is
    already exact and the alternation changes nothing but the cost.
    """
    b = T.matvec3(inv, m.r.sum(0))
    if m.r.shape[0] < 2:
        return b
    for _ in range(iterations):
        n, _ = unit(b)
        rho, _, _ = group_albedo(m, n)
        mean = rho.mean(0, keepdim=True)
        ok = (rho > 0) & (mean > 0)
        rel = torch.where(ok, rho / torch.where(ok, mean, torch.ones_like(mean)), torch.ones_like(rho))
        A = (m.Q * (rel * rel)[:, None, None, :]).sum(0)
        inv_p, _ = T.inverse3(A)
        b = T.matvec3(inv_p, (m.r * rel[:, None]).sum(0))
    return b


def albedo_iterations(requested, L, selectors, groups, num_groups) -> int:
    """Alternation steps: as requested, or (None) 3 when the channels see different lights
    and 0 when a joint solve is already exact; never without three observations per group."""
    if not group_counts_ok(groups, num_groups):
        return 0
    if requested is None:
        return 0 if channels_share_lights(L, selectors) else 3
    return int(requested)


def residual_rms(m: Moments, p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Weighted RMS residual ``(M,)`` of the fit with the least-squares albedo per group."""
    explained = (p * p / torch.clamp(q, min=torch.finfo(q.dtype).tiny)).sum(0)
    ss = torch.clamp(m.S.sum(0) - explained, min=0.0)
    return torch.sqrt(ss / torch.clamp(m.wsum, min=torch.finfo(ss.dtype).tiny))


def finalize_tensors(b: torch.Tensor, m: Moments, cond: torch.Tensor, *, max_condition: float = 1e3,
                     min_count: int = 3, finite_inputs: bool = False) -> dict[str, torch.Tensor]:
    """The per-pixel outputs as tensors with pixels last (see :func:`finalize`)."""
    if not finite_inputs:
        finite = torch.isfinite(b).all(0)
        b = torch.nan_to_num(b, nan=0.0, posinf=0.0, neginf=0.0)
    n, norm = unit(b)
    valid = (norm > 0) & (m.count >= min_count) & (cond <= max_condition) & (n[2] > 0)
    if not finite_inputs:
        valid = valid & finite
    flat = torch.zeros((3, 1), dtype=n.dtype, device=n.device)
    flat[2] = 1.0
    n = torch.where(valid, n, flat)
    rho, p, q = group_albedo(m, n)
    res = residual_rms(m, p, q)
    zero = torch.zeros((), dtype=n.dtype, device=n.device)
    # Moments of huge but finite inputs can overflow to Inf in the products (a 1e30 observation
    # squares to Inf in float32), also when every input is finite: outputs are always cleaned.
    rho = torch.nan_to_num(rho, nan=0.0, posinf=0.0, neginf=0.0)
    res = torch.nan_to_num(res, nan=0.0, posinf=torch.finfo(res.dtype).max, neginf=0.0)  # overflowed: a huge misfit
    cond = torch.nan_to_num(cond, nan=COND_CAP, posinf=COND_CAP, neginf=COND_CAP)
    return {"normals": n, "albedo": torch.where(valid, rho, zero), "residual": torch.where(valid, res, zero),
            "condition": cond.expand(n.shape[1]) if cond.numel() == 1 else cond, "mask": valid,
            "count": m.count}


def to_result(t: dict[str, torch.Tensor], shape: tuple[int, int], meta: dict | None = None) -> NormalResult:
    """Tensors with pixels last -> a :class:`NormalResult` of ``(H, W, ...)`` numpy arrays."""
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
    if len(parts) == 1:
        return parts[0]
    return {k: torch.cat([p[k] for p in parts], dim=-1) for k in parts[0]}


def finalize(b: torch.Tensor, m: Moments, cond: torch.Tensor, shape: tuple[int, int], *,
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
