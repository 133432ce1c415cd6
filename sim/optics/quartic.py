"""Float64 reference for the swept arc: the full torus quartic, solved and polished.

The torus ``(rho - rho_c)^2 + (z - z_c)^2 = r1^2`` met by ``p(t) = o + t d`` (``|d| = 1``) is

    (|q(t)|^2 + rho_c^2 - r1^2)^2 = 4 rho_c^2 (x(t)^2 + y(t)^2),   q = p - (0, 0, z_c),

a quartic in ``t``. Its roots come from the eigenvalues of the companion matrices (batched,
numpy) and are polished by Newton steps on the quartic. Slow (for tests and the benchmark's
error column), but independent of the convex-set reasoning of :mod:`sim.optics.torus`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["torus_quartic", "torus_roots", "first_outer_hit"]


def torus_quartic(o, d, r1: float, rho_c: float, z_c: float) -> np.ndarray:
    """Coefficients (N, 5), highest power first, of the torus quartic along each ray.

    Examples
    --------
    >>> c = torus_quartic(np.array([[50.0, 0, 6]]), np.array([[-1.0, 0, 0]]), 13.5, 22.5, 6.0)
    >>> sorted(np.round(np.roots(c[0]).real, 6).tolist())
    [14.0, 41.0, 59.0, 86.0]
    """
    o = np.asarray(o, dtype=np.float64).reshape(-1, 3).copy()
    d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
    o[:, 2] -= z_c
    p = np.einsum("ij,ij->i", o, d)
    q = np.einsum("ij,ij->i", o, o)
    k = q + rho_c ** 2 - r1 ** 2
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
    g = o[:, 0] ** 2 + o[:, 1] ** 2
    R2 = 4.0 * rho_c ** 2
    # (t^2 + 2 p t + k)^2 - R2 (a t^2 + 2 b t + g)
    return np.stack([np.ones_like(p), 4 * p, 4 * p * p + 2 * k - R2 * a, 4 * p * k - 2 * R2 * b, k * k - R2 * g], 1)


def torus_roots(o, d, r1: float, rho_c: float, z_c: float, polish: int = 3) -> np.ndarray:
    """Real roots (N, 4) of the torus quartic, ascending, NaN-free: missing roots are ``+inf``."""
    c = torus_quartic(o, d, r1, rho_c, z_c)
    N = len(c)
    comp = np.zeros((N, 4, 4))
    comp[:, 0, :] = -c[:, 1:]
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    ev = np.linalg.eigvals(comp)
    real = np.abs(ev.imag) <= 1e-6 * np.maximum(1.0, np.abs(ev.real))
    t = np.where(real, ev.real, np.inf)
    for _ in range(polish):
        tt = np.where(np.isfinite(t), t, 0.0)
        f = (((c[:, 0:1] * tt + c[:, 1:2]) * tt + c[:, 2:3]) * tt + c[:, 3:4]) * tt + c[:, 4:5]
        df = ((4 * c[:, 0:1] * tt + 3 * c[:, 1:2]) * tt + 2 * c[:, 2:3]) * tt + c[:, 3:4]
        step = np.where(np.abs(df) > 1e-300, f / np.where(df == 0, 1.0, df), 0.0)
        t = np.where(np.isfinite(t), t - step, t)
    return np.sort(t, axis=1)


def first_outer_hit(o, d, r1: float, rho_c: float, z_c: float, z_lo: float, z_hi: float, t_min: float = 1e-9):
    """First ``t > t_min`` where each ray meets the outer half of the arc within ``[z_lo, z_hi]`` (``inf`` if none)."""
    o = np.asarray(o, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
    t = torus_roots(o, d, r1, rho_c, z_c)
    tt = np.where(np.isfinite(t), t, 0.0)
    p = o[:, None, :] + tt[..., None] * d[:, None, :]
    rho = np.hypot(p[..., 0], p[..., 1])
    ok = np.isfinite(t) & (t > t_min) & (rho >= rho_c) & (p[..., 2] >= z_lo) & (p[..., 2] <= z_hi)
    return np.where(ok, t, np.inf).min(axis=1)
