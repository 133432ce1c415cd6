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
Every function takes numpy arrays (the CPU) or torch tensors (any device) alike and answers in
the same library (:mod:`pipeline.normals._xp`).

:func:`finalize` is the one place that turns a raw solve into a
:class:`~pipeline.normals.result.NormalResult`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.normals import _linalg3 as A3
from pipeline.normals import _xp
from pipeline.normals._inputs import group_counts_ok
from pipeline.normals._xp import Array
from pipeline.normals.result import COND_CAP, NormalResult


@dataclass
class Moments:
    """Per-group normal-equation moments of every pixel.

    Q : (G, 3, 3, M) or (G, 3, 3, 1) when the same for every pixel
    r : (G, 3, M)
    S : (G, M)
    wsum : (M,) total weight; count : (M,) observations with non-zero weight
    """

    Q: Array
    r: Array
    S: Array
    wsum: Array
    count: Array


def group_selectors(groups: Array | None, num_groups: int, n: int) -> list:
    """One selector per albedo group: a slice when the group's observations are evenly spaced
    (the usual pattern-major, channel-minor order: no copy), else an index array (in the
    library and on the device of ``groups``)."""
    if groups is None:
        return [slice(None)]
    g_all = _xp.to_numpy(groups)
    out = []
    for g in range(num_groups):
        idx = np.flatnonzero(g_all == g)
        step = int(idx[1] - idx[0]) if idx.size > 1 else 1
        if idx.size and step > 0 and np.array_equal(idx, np.arange(idx[0], idx[0] + step * idx.size, step)):
            out.append(slice(int(idx[0]), int(idx[0]) + step * (idx.size - 1) + 1, step))
        else:
            out.append(_xp.index_like(groups, idx))
    return out


def channels_share_lights(L: Array, selectors: list, rtol: float = 1e-4) -> bool:
    """True when every group's lights are one scalar multiple of the first group's.

    Then a joint solve is exact whatever the per-group albedo (white patterns: the channels
    of a pattern see the same light), and the per-group alternation can be skipped.
    ``L`` is ``(N, 3)`` or ``(N, 3, M)``; groups of different sizes never share.
    """
    if len(selectors) < 2:
        return True
    f64 = _xp.namespace(L).float64
    ref = _xp.astype(L[selectors[0]], f64)
    ref_norm = float((ref * ref).sum())
    for sel in selectors[1:]:
        Lg = _xp.astype(L[sel], f64)
        if Lg.shape != ref.shape:
            return False
        a = float((Lg * ref).sum()) / max(ref_norm, 1e-300)
        if float(((Lg - a * ref) ** 2).sum()) > (rtol ** 2) * max(float((Lg * Lg).sum()), 1e-300):
            return False
    return True


def gram_shared(L: Array, w: Array | None) -> Array:
    """``sum_k w_k L_k L_k^T`` for shared lights ``(N, 3)``: ``(3, 3, 1)`` or ``(3, 3, M)``."""
    outer = (L[:, :, None] * L[:, None, :]).reshape(L.shape[0], 9)
    if w is None:
        return outer.sum(0).reshape(3, 3, 1)
    return (outer.T @ w).reshape(3, 3, -1)


def gram_pixel(L: Array, w: Array | None) -> Array:
    """``sum_k w_k L_k L_k^T`` for per-pixel lights ``(N, 3, M)``: ``(3, 3, M)``."""
    xp = _xp.namespace(L)
    wl = L if w is None else L * w[:, None, :]
    rows = [xp.stack([(wl[:, i] * L[:, j]).sum(0) for j in range(3)]) for i in range(3)]
    return xp.stack(rows)


def condition(L: Array, w: Array | None) -> Array:
    """Condition number ``(M,)`` (or ``(1,)``) of the weighted light matrix, computed in float64.

    Float32 rounding alone puts the smallest eigenvalue of a rank-deficient Gram matrix near
    ``1e-7`` of the largest, i.e. a condition number of only a few thousand: too close to the
    masking threshold to tell "rank-deficient" from "merely oblique" reliably.
    """
    f64 = _xp.namespace(L).float64
    L64 = _xp.astype(L, f64)
    w64 = None if w is None else _xp.astype(w, f64)
    A = gram_shared(L64, w64) if L.ndim == 2 else gram_pixel(L64, w64)
    return _xp.astype(A3.condition_from_gram(A), L.dtype)


def moments(I: Array, L: Array, w: Array | None, selectors: list,
            Q: Array | None = None, count: Array | None = None) -> Moments:
    """Moments of observations ``I`` ``(N, M)`` with weights ``w`` ``(N, M)`` (None: all 1).

    ``Q`` ``(G, 3, 3, M|1)`` may be passed when it is known (it does not depend on ``I``), and
    ``count`` ``(M,)`` (observations with non-zero weight) when the caller has it: a boolean
    reduction over ``(N, M)`` is slow on the CPU.
    """
    xp = _xp.namespace(I)
    Qs, rs, Ss = [], [], []
    for sel in selectors:
        Ig, Lg = I[sel], L[sel]
        wg = None if w is None else w[sel]
        wI = Ig if wg is None else wg * Ig
        Ss.append((wI * Ig).sum(0))
        if Lg.ndim == 2:
            rs.append(Lg.T @ wI)
            if Q is None:
                Qs.append(gram_shared(Lg, wg))
        else:
            rs.append((Lg * wI[:, None, :]).sum(0))
            if Q is None:
                Qs.append(gram_pixel(Lg, wg))
    if Q is None:
        width = max(q.shape[-1] for q in Qs)
        Q = xp.stack([xp.broadcast_to(q, (3, 3, width)) for q in Qs])
    M = I.shape[1]
    if w is None:
        wsum = _xp.full(I, (M,), float(I.shape[0]), I.dtype)
        count = _xp.full(I, (M,), I.shape[0], xp.int32)
    else:
        wsum = w.sum(0)
        count = (w > 0).sum(0, dtype=xp.int32) if count is None else _xp.astype(count, xp.int32)
    return Moments(Q=Q, r=xp.stack(rs), S=xp.stack(Ss), wsum=wsum, count=count)


def quad(Q: Array, n: Array) -> Array:
    """``n^T Q_g n`` per group and pixel: ``(G, M)``."""
    nn = (n[:, None] * n[None]).reshape(9, -1)
    if Q.shape[-1] == 1:  # the same Q at every pixel: one (G, 9) @ (9, M) product
        return Q.reshape(Q.shape[0], 9) @ nn
    return (Q.reshape(Q.shape[0], 9, -1) * nn[None]).sum(1)


def unit(b: Array) -> tuple[Array, Array]:
    """``(b / |b|, |b|)`` for ``(3, M)``; zero vectors stay zero."""
    xp = _xp.namespace(b)
    norm = xp.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    return b / xp.clip(norm, xp.finfo(b.dtype).tiny, None), norm


def group_albedo(m: Moments, n: Array) -> tuple[Array, Array, Array]:
    """``(rho, p, q)``: albedo ``(G, M)`` given the normal, with ``p = n . r_g``, ``q = n^T Q_g n``.

    ``q = sum w s^2 >= 0``, and ``q = 0`` forces ``p = sum w I s = 0``, so a clamped division
    gives albedo 0 there without a branch.
    """
    p = m.r[:, 0] * n[0] + m.r[:, 1] * n[1] + m.r[:, 2] * n[2]
    q = quad(m.Q, n)
    xp = _xp.namespace(q)
    return p / xp.clip(q, xp.finfo(q.dtype).tiny, None), p, q


def solve(m: Moments, inv: Array, iterations: int = 0) -> Array:
    """``b`` ``(3, M)`` from moments and the inverse ``(3, 3, M|1)`` of ``sum_g Q_g``; then
    ``iterations`` per-group albedo alternation steps (only meaningful with several groups).

    The alternation rescales the *model*, not the data: with relative albedo ``s_g`` the
    system becomes ``(sum_g s_g^2 Q_g) b = sum_g s_g r_g``, so noisy dim channels are not
    amplified. When every group sees the same lights (white patterns) the joint solve is
    already exact and the alternation changes nothing but the cost.
    """
    xp = _xp.namespace(m.r)
    b = A3.matvec3(inv, m.r.sum(0))
    if m.r.shape[0] < 2:
        return b
    for _ in range(iterations):
        n, _ = unit(b)
        rho, _, _ = group_albedo(m, n)
        mean = rho.mean(0, keepdims=True)
        ok = (rho > 0) & (mean > 0)
        rel = xp.where(ok, rho / xp.where(ok, mean, xp.ones_like(mean)), xp.ones_like(rho))
        A = (m.Q * (rel * rel)[:, None, None, :]).sum(0)
        inv_p, _ = A3.inverse3(A)
        b = A3.matvec3(inv_p, (m.r * rel[:, None]).sum(0))
    return b


def albedo_iterations(requested, L, selectors, groups, num_groups) -> int:
    """Alternation steps: as requested, or (None) 3 when the channels see different lights
    and 0 when a joint solve is already exact; never without three observations per group."""
    if not group_counts_ok(groups, num_groups):
        return 0
    if requested is None:
        return 0 if channels_share_lights(L, selectors) else 3
    return int(requested)


def residual_rms(m: Moments, p: Array, q: Array) -> Array:
    """Weighted RMS residual ``(M,)`` of the fit with the least-squares albedo per group."""
    xp = _xp.namespace(q)
    explained = (p * p / xp.clip(q, xp.finfo(q.dtype).tiny, None)).sum(0)
    ss = xp.clip(m.S.sum(0) - explained, 0.0, None)
    return xp.sqrt(ss / xp.clip(m.wsum, xp.finfo(ss.dtype).tiny, None))


def finalize_tensors(b: Array, m: Moments, cond: Array, *, max_condition: float = 1e3,
                     min_count: int = 3, finite_inputs: bool = False) -> dict[str, Array]:
    """The per-pixel outputs as arrays with pixels last (see :func:`finalize`)."""
    xp = _xp.namespace(b)
    if not finite_inputs:
        finite = xp.isfinite(b).all(0)
        b = xp.nan_to_num(b, nan=0.0, posinf=0.0, neginf=0.0)
    n, norm = unit(b)
    valid = (norm > 0) & (m.count >= min_count) & (cond <= max_condition) & (n[2] > 0)
    if not finite_inputs:
        valid = valid & finite
    flat = xp.zeros_like(n[:, :1])
    flat[2] = 1.0
    n = xp.where(valid, n, flat)
    rho, p, q = group_albedo(m, n)
    res = residual_rms(m, p, q)
    # Moments of huge but finite inputs can overflow to Inf in the products (a 1e30 observation
    # squares to Inf in float32), also when every input is finite: outputs are always cleaned.
    rho = xp.nan_to_num(rho, nan=0.0, posinf=0.0, neginf=0.0)
    res = xp.nan_to_num(res, nan=0.0, posinf=xp.finfo(res.dtype).max, neginf=0.0)  # overflowed: a huge misfit
    cond = xp.nan_to_num(cond, nan=COND_CAP, posinf=COND_CAP, neginf=COND_CAP)
    return {"normals": n, "albedo": xp.where(valid, rho, 0.0), "residual": xp.where(valid, res, 0.0),
            "condition": xp.broadcast_to(cond, (n.shape[1],)) if math.prod(cond.shape) == 1 else cond,
            "mask": valid, "count": m.count}


def to_result(t: dict[str, Array], shape: tuple[int, int], meta: dict | None = None) -> NormalResult:
    """Arrays with pixels last -> a :class:`NormalResult` of ``(H, W, ...)`` numpy arrays."""
    H, W = shape
    out_dtype = np.float64 if _xp.numpy_dtype(t["normals"].dtype) == np.float64 else np.float32

    def out(x):  # (..., M) -> (H, W, ...), one transposing copy
        a = _xp.pixels_first(x)
        return a.reshape((H, W) + a.shape[1:])

    return NormalResult(
        normals=out(t["normals"]).astype(out_dtype, copy=False),
        albedo=out(t["albedo"]).astype(out_dtype, copy=False),
        residual=out(t["residual"]).astype(out_dtype, copy=False),
        condition=out(t["condition"]).astype(out_dtype, copy=False),
        mask=out(t["mask"]).astype(bool, copy=False),
        count=out(t["count"]).astype(np.int32, copy=False),
        meta=dict(meta or {}),
    )


def concat(parts: list[dict[str, Array]]) -> dict[str, Array]:
    """Join per-chunk outputs along the pixel axis."""
    if len(parts) == 1:
        return parts[0]
    xp = _xp.namespace(parts[0]["normals"])
    return {k: xp.concatenate([p[k] for p in parts], axis=-1) for k in parts[0]}


def finalize(b: Array, m: Moments, cond: Array, shape: tuple[int, int], *,
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
