"""Batched per-pixel linear algebra shared by the normal solvers (torch, one CPU/CUDA path).

Pixels are flattened: observations ``I`` are ``(N, M)`` (``N`` observations, ``M = H * W``
pixels), weights ``w`` are ``(N, M)`` and light vectors are either shared ``(N, 3)`` (far
field) or per pixel ``(N, M, 3)`` (near field). Every function here is finite on any input:
singular systems give a zero solution and an infinite-ish (capped) condition number that the
caller turns into a mask.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.normals.result import COND_CAP


def torch_dtype(dtype) -> torch.dtype:
    """Map ``"float32"``, ``np.float64``, ``torch.float32`` ... to a torch floating dtype.

    Examples
    --------
    >>> torch_dtype("float64")
    torch.float64
    >>> torch_dtype(np.float32)
    torch.float32
    """
    if isinstance(dtype, torch.dtype):
        out = dtype
    else:
        out = getattr(torch, np.dtype(dtype).name, None)
    if out not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be float32 or float64, got {dtype!r}")
    return out


def to_tensor(x, dtype: torch.dtype, device) -> torch.Tensor:
    """numpy array (any dtype) or tensor -> floating tensor on ``device`` (no copy when possible)."""
    if isinstance(x, torch.Tensor):
        return x.to(device=device, dtype=dtype)
    a = np.asarray(x)
    if a.dtype.kind not in "fiub":
        raise ValueError(f"expected a numeric array, got dtype {a.dtype}")
    if a.dtype == np.uint16 or a.dtype == np.uint32:
        a = a.astype(np.int64)  # torch has no unsigned 16/32-bit arithmetic on every build
    if not a.flags.writeable:
        a = np.array(a)  # torch refuses read-only (e.g. broadcast) arrays without copying
    return torch.as_tensor(a, device=device).to(dtype)


def sym3_eigvals(A: torch.Tensor) -> torch.Tensor:
    """Eigenvalues ``(3, M)`` (descending) of symmetric matrices ``(3, 3, M)``, closed form.

    The trigonometric method (Smith 1961): much faster than a batched iterative
    eigensolver for millions of 3x3 matrices, and exact enough to decide conditioning.

    Examples
    --------
    >>> A = torch.diag(torch.tensor([3.0, 1.0, 2.0], dtype=torch.float64))[..., None]
    >>> np.round(sym3_eigvals(A).numpy()[:, 0], 9).tolist()
    [3.0, 2.0, 1.0]
    """
    a00, a11, a22 = A[0, 0], A[1, 1], A[2, 2]
    a01, a02, a12 = A[0, 1], A[0, 2], A[1, 2]
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = torch.sqrt(p2 / 6.0)
    safe_p = torch.where(p > 0, p, torch.ones_like(p))
    b00, b11, b22 = (a00 - q) / safe_p, (a11 - q) / safe_p, (a22 - q) / safe_p
    b01, b02, b12 = a01 / safe_p, a02 / safe_p, a12 / safe_p
    det_b = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    r = torch.clamp(det_b / 2.0, -1.0, 1.0)
    phi = torch.acos(r) / 3.0
    e1 = q + 2.0 * p * torch.cos(phi)
    e3 = q + 2.0 * p * torch.cos(phi + 2.0 * math.pi / 3.0)
    e2 = 3.0 * q - e1 - e3
    return torch.stack([e1, e2, e3])


def condition_from_gram(A: torch.Tensor) -> torch.Tensor:
    """Condition number ``(M,)`` of the light matrix whose Gram matrix is ``A`` ``(3, 3, M)``.

    ``cond(L) = sqrt(lambda_max(A) / lambda_min(A))``; a zero or negative ``lambda_min`` (a
    singular or rank-deficient light matrix) reads as :data:`COND_CAP`. Always finite.
    """
    ev = sym3_eigvals(A)
    lmax, lmin = ev[0], ev[2]
    ratio = lmax / torch.where(lmin > 0, lmin, torch.ones_like(lmin))
    cond = torch.sqrt(torch.clamp(ratio, min=1.0))
    bad = (lmin <= 0) | (lmax <= 0) | ~torch.isfinite(cond)
    return torch.where(bad, torch.full_like(cond, COND_CAP), torch.clamp(cond, max=COND_CAP))


def inverse3(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of matrices ``(3, 3, M)`` by the adjugate, and a mask ``(M,)`` of invertible ones.

    Singular matrices give a zero inverse (never Inf/NaN); the caller masks them.
    """
    a, b, c = A[0, 0], A[0, 1], A[0, 2]
    d, e, f = A[1, 0], A[1, 1], A[1, 2]
    g, h, i = A[2, 0], A[2, 1], A[2, 2]
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * c00 + b * c01 + c * c02
    adj = torch.stack([
        torch.stack([c00, c * h - b * i, b * f - c * e]),
        torch.stack([c01, a * i - c * g, c * d - a * f]),
        torch.stack([c02, b * g - a * h, a * e - b * d]),
    ])
    ok = (det != 0) & torch.isfinite(det)
    inv_det = torch.where(ok, 1.0 / torch.where(ok, det, torch.ones_like(det)), torch.zeros_like(det))
    inv = adj * inv_det
    ok = ok & torch.isfinite(inv).all(0).all(0)
    return torch.where(ok, inv, torch.zeros_like(inv)), ok


def matvec3(A: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``A x`` per pixel: ``(3, 3, M)`` or ``(3, 3, 1)`` times ``(3, M)`` -> ``(3, M)``."""
    return A[:, 0] * x[0] + A[:, 1] * x[1] + A[:, 2] * x[2]


def dot3(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-pixel dot product of ``(3, M)`` vectors -> ``(M,)``."""
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def project(L: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """``s_k = n . L_k`` per observation and pixel ``(N, M)``; ``L`` is ``(N, 3)`` or ``(N, 3, M)``,
    ``n`` is ``(3, M)``."""
    if L.dim() == 2:
        return L @ n
    return L[:, 0] * n[0] + L[:, 1] * n[1] + L[:, 2] * n[2]
