"""Batched per-pixel 3x3 linear algebra shared by the normal solvers, on numpy arrays or torch
tensors alike (:mod:`pipeline.normals._xp`: one code for the CPU and CUDA).

Pixels are flattened: observations ``I`` are ``(N, M)`` (``N`` observations, ``M = H * W``
pixels), weights ``w`` are ``(N, M)`` and light vectors are either shared ``(N, 3)`` (far
field) or per pixel ``(N, M, 3)`` (near field). Every function here is finite on any input:
singular systems give a zero solution and an infinite-ish (capped) condition number that the
caller turns into a mask.
"""

from __future__ import annotations

import math

from pipeline.normals._xp import Array, namespace
from pipeline.normals.result import COND_CAP


def sym3_eigvals(A: Array) -> Array:
    """Eigenvalues ``(3, M)`` (descending) of symmetric matrices ``(3, 3, M)``, closed form.

    The trigonometric method (Smith 1961): much faster than a batched iterative
    eigensolver for millions of 3x3 matrices, and exact enough to decide conditioning.

    Examples
    --------
    >>> import numpy as np
    >>> A = np.diag([3.0, 1.0, 2.0])[..., None]
    >>> np.round(sym3_eigvals(A)[:, 0], 9).tolist()
    [3.0, 2.0, 1.0]
    """
    xp = namespace(A)
    a00, a11, a22 = A[0, 0], A[1, 1], A[2, 2]
    a01, a02, a12 = A[0, 1], A[0, 2], A[1, 2]
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = xp.sqrt(p2 / 6.0)
    safe_p = xp.where(p > 0, p, xp.ones_like(p))
    b00, b11, b22 = (a00 - q) / safe_p, (a11 - q) / safe_p, (a22 - q) / safe_p
    b01, b02, b12 = a01 / safe_p, a02 / safe_p, a12 / safe_p
    det_b = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    r = xp.clip(det_b / 2.0, -1.0, 1.0)
    phi = xp.arccos(r) / 3.0
    e1 = q + 2.0 * p * xp.cos(phi)
    e3 = q + 2.0 * p * xp.cos(phi + 2.0 * math.pi / 3.0)
    e2 = 3.0 * q - e1 - e3
    return xp.stack([e1, e2, e3])


def condition_from_gram(A: Array) -> Array:
    """Condition number ``(M,)`` of the light matrix whose Gram matrix is ``A`` ``(3, 3, M)``.

    ``cond(L) = sqrt(lambda_max(A) / lambda_min(A))``; a zero or negative ``lambda_min`` (a
    singular or rank-deficient light matrix) reads as :data:`COND_CAP`. Always finite.
    """
    xp = namespace(A)
    ev = sym3_eigvals(A)
    lmax, lmin = ev[0], ev[2]
    ratio = lmax / xp.where(lmin > 0, lmin, xp.ones_like(lmin))
    cond = xp.sqrt(xp.clip(ratio, 1.0, None))
    bad = (lmin <= 0) | (lmax <= 0) | ~xp.isfinite(cond)
    return xp.where(bad, xp.full_like(cond, COND_CAP), xp.clip(cond, None, COND_CAP))


def inverse3(A: Array) -> tuple[Array, Array]:
    """Inverse of matrices ``(3, 3, M)`` by the adjugate, and a mask ``(M,)`` of invertible ones.

    Singular matrices give a zero inverse (never Inf/NaN); the caller masks them.
    """
    xp = namespace(A)
    a, b, c = A[0, 0], A[0, 1], A[0, 2]
    d, e, f = A[1, 0], A[1, 1], A[1, 2]
    g, h, i = A[2, 0], A[2, 1], A[2, 2]
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * c00 + b * c01 + c * c02
    adj = xp.stack([
        xp.stack([c00, c * h - b * i, b * f - c * e]),
        xp.stack([c01, a * i - c * g, c * d - a * f]),
        xp.stack([c02, b * g - a * h, a * e - b * d]),
    ])
    ok = (det != 0) & xp.isfinite(det)
    inv_det = xp.where(ok, 1.0 / xp.where(ok, det, xp.ones_like(det)), xp.zeros_like(det))
    inv = adj * inv_det
    ok = ok & xp.isfinite(inv).all(0).all(0)
    return xp.where(ok, inv, xp.zeros_like(inv)), ok


def matvec3(A: Array, x: Array) -> Array:
    """``A x`` per pixel: ``(3, 3, M)`` or ``(3, 3, 1)`` times ``(3, M)`` -> ``(3, M)``."""
    return A[:, 0] * x[0] + A[:, 1] * x[1] + A[:, 2] * x[2]


def project(L: Array, n: Array) -> Array:
    """``s_k = n . L_k`` per observation and pixel ``(N, M)``; ``L`` is ``(N, 3)`` or ``(N, 3, M)``,
    ``n`` is ``(3, M)``."""
    if L.ndim == 2:
        return L @ n
    return L[:, 0] * n[0] + L[:, 1] * n[1] + L[:, 2] * n[2]
