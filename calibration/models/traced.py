"""Traced model: the ray tracer's fields ``V_i`` with fitted per-LED, per-channel gains.

With the true normals known on the cap, ``I_pj(x) = rho sum_i sigma_ij W_p[i, j] b_p
max(0, n(x) . V_i(x))`` is linear in the gains ``sigma_ij`` (``rho = 1``: the gel's albedo is
uniform; exposure and the ``1 / pi`` fold into ``sigma``), so they are fitted per camera
channel by non-negative least squares over all patterns. Any pattern, captured or not, then
has the light field ``sim.illumination_model.light_matrices(V, W, b, gains=sigma)``.

Optionally (``basis`` given, see :mod:`calibration.models.led_geometry`) the fit also corrects
each LED's position and tilt to first order, ``V_i = V_i^0 + sum_k theta_ik D_ik``: gains
(NNLS) and the corrections ``theta`` (ridge-damped linear least squares with the gains held,
a Gauss-Newton step since the model is linear in ``theta`` where the pixel stays lit)
alternate for ``geometry_iterations`` rounds.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.models.base import LightFieldModel
from calibration.samples import Samples
from pipeline.base.errors import UserError
from sim.illumination_model import light_matrices

__all__ = ["TracedModel", "nnls_tall", "nnls_on_gram", "MAX_GRAM_CONDITION"]


class TracedModel(LightFieldModel):
    """Gains on given LED fields.

    Parameters
    ----------
    V : ndarray, shape (L, H, W, 3)
        Vector irradiance per LED (an ``IlluminationModel.V``).
    drive : ndarray, shape (P, L, 3)
    brightness : ndarray, shape (P,), optional
    basis : ndarray, shape (L, 5, H, W, 3), optional
        ``dV / dtheta`` (:func:`calibration.models.led_geometry.geometry_basis`); enables the
        LED position/tilt corrections.
    geometry_iterations : int
        Alternations of gains and geometry.
    geometry_ridge : float
        Damping of the geometry step, relative to the mean diagonal of the normal matrix.
    max_geometry_samples : int
        Pixels (seeded draw) used for the geometry step.
    """

    name = "traced"

    def __init__(self, V: np.ndarray, drive: np.ndarray, brightness: np.ndarray | None = None,
                 basis: np.ndarray | None = None, geometry_iterations: int = 4, geometry_ridge: float = 1e-3,
                 max_geometry_samples: int = 20000):
        V = np.asarray(V, dtype=np.float64)
        drive = np.asarray(drive, dtype=np.float64)
        if V.ndim != 4 or V.shape[-1] != 3:
            raise UserError(f"traced model: V must have shape (L, H, W, 3), got {V.shape}")
        if drive.ndim != 3 or drive.shape[1:] != (V.shape[0], 3):
            raise UserError(f"traced model: the capture's drive {drive.shape} does not match the illumination "
                            f"model's {V.shape[0]} LEDs (expected (P, {V.shape[0]}, 3))")
        if basis is not None:
            basis = np.asarray(basis, dtype=np.float64)
            if basis.ndim != 5 or basis.shape[0] != V.shape[0] or basis.shape[2:] != V.shape[1:]:
                raise UserError(f"traced model: the geometry basis must have shape ({V.shape[0]}, K, "
                                f"{V.shape[1]}, {V.shape[2]}, 3), got {basis.shape}")
        self.V0 = V
        self.V = V
        self.basis = basis
        self.theta: np.ndarray | None = None
        self.geometry_iterations, self.geometry_ridge = int(geometry_iterations), float(geometry_ridge)
        self.max_geometry_samples = int(max_geometry_samples)
        self.drive = drive
        self.brightness = np.ones(len(drive)) if brightness is None else np.asarray(brightness, dtype=np.float64)
        self.gains: np.ndarray | None = None
        self.flat = None
        self.num_patterns, self.num_channels = len(drive), 3

    def fit(self, samples: Samples, reference: np.ndarray | None = None) -> dict[str, Any]:
        if samples.shape != self.V.shape[1:3]:
            raise UserError(f"traced model: the illumination model is {self.V.shape[1:3]} pixels but the capture is "
                            f"{samples.shape}")
        if samples.intensities.shape[1:] != (len(self.drive), 3):
            raise UserError(f"traced model: samples have {samples.intensities.shape[1:]} pattern-channels, the drive "
                            f"has ({len(self.drive)}, 3)")
        V0 = self.V0[:, samples.rows, samples.cols]  # (L, N, 3)
        rounds = self.geometry_iterations if self.basis is not None else 0
        theta = np.zeros((self.V0.shape[0], 0 if self.basis is None else self.basis.shape[1]))
        for it in range(rounds + 1):
            Vs = V0 if self.basis is None else V0 + np.einsum("lk,lknc->lnc", theta, self._basis_at(samples))
            gains, resid = self._fit_gains(Vs, samples)
            if it == rounds:
                break
            theta = theta + self._geometry_step(Vs, gains, samples)
        self.gains = gains
        if self.basis is not None:
            self.theta = theta
            self.V = self.V0 + np.einsum("lk,lkhwc->lhwc", theta, self.basis)
        rep = self._fit_report(samples)
        rep["residual_rms_dn"] = resid
        if self.theta is not None:
            rep["led_position_correction_mm"] = self.theta[:, :3].tolist()
            rep["led_tilt_correction_deg"] = np.degrees(self.theta[:, 3:5]).tolist()
        return rep

    def _basis_at(self, samples: Samples) -> np.ndarray:
        return self.basis[:, :, samples.rows, samples.cols]  # (L, K, N, 3)

    def _fit_gains(self, Vs: np.ndarray, samples: Samples) -> tuple[np.ndarray, float]:
        """NNLS per camera channel for fields ``Vs (L, N, 3)`` at the samples; returns gains and RMS residual.

        The system of channel ``j`` has a row per pixel n and pattern p, ``A[(n, p), l] = s[n, l]
        w[p, l]`` (shading times drive), so its Gram matrix is the elementwise product of two small
        ones, ``A^T A = (s^T s) * (w^T w)``, and ``A^T b = sum_n s[n] * (B w)[n]``: built in
        O(N L^2) rather than O(N P L^2), and solved on its Cholesky factor (:func:`nnls_on_gram`).
        When that Gram matrix is too ill-conditioned for its squared condition number
        (:data:`MAX_GRAM_CONDITION`) the rows are built and solved on their QR factor
        (:func:`nnls_tall`).
        """
        s = np.maximum(np.einsum("lnk,nk->nl", Vs, samples.normals), 0.0)  # (N, L)
        w = self.drive * self.brightness[:, None, None]  # (P, L, 3)
        n_led = Vs.shape[0]
        gains = np.zeros((n_led, 3))
        resid = []
        ss = s.T @ s  # (L, L)
        s_max = s.max(0, initial=0.0)  # s >= 0 already
        for j in range(3):
            wj = w[:, :, j]  # (P, L)
            B = samples.intensities[:, :, j].astype(np.float64)  # (N, P)
            w_max = np.abs(wj).max(0)
            active = (s_max > 0) & (w_max > 0)  # the columns of A that are not zero
            g = np.zeros(n_led)
            # Column scaling keeps NNLS well conditioned (V is ~1e-4 W/mm^2): by each column's largest entry.
            sc = np.maximum((s_max * w_max)[active], 1e-300)
            gram = (ss * (wj.T @ wj))[np.ix_(active, active)] / np.outer(sc, sc)
            atb = np.einsum("nl,nl->l", s, B @ wj)[active] / sc
            solved = nnls_on_gram(gram, atb, float(np.sum(B * B)))
            if solved is None:
                A = (s[:, None, :] * wj[None, :, :]).reshape(-1, n_led)  # (N * P, L)
                solved = nnls_tall(A[:, active] / sc, B.reshape(-1))
            g_act, rn = solved
            g[active] = g_act / sc
            gains[:, j] = g
            resid.append(rn / np.sqrt(max(B.size, 1)))
        return gains, float(np.sqrt(np.mean(np.square(resid))))

    def _geometry_step(self, Vs: np.ndarray, gains: np.ndarray, samples: Samples) -> np.ndarray:
        """Gauss-Newton step ``dtheta (L, K)`` with the gains held (ridge-damped, columns scaled)."""
        rng = np.random.default_rng(0)
        idx = np.arange(len(samples))
        if len(idx) > self.max_geometry_samples:
            idx = np.sort(rng.choice(idx, self.max_geometry_samples, replace=False))
        n = samples.normals[idx]
        V = Vs[:, idx]
        D = self._basis_at(samples)[:, :, idx]  # (L, K, N, 3)
        shade = np.einsum("lnc,nc->nl", V, n)
        lit = shade > 0
        w = self.drive * self.brightness[:, None, None] * gains[None]  # (P, L, 3)
        pred = np.einsum("plj,nl->npj", w, np.where(lit, shade, 0.0))
        r = (samples.intensities[idx].astype(np.float64) - pred).reshape(-1)
        nD = np.einsum("lknc,nc->nlk", D, n) * lit[..., None]  # (N, L, K)
        n_led, k = D.shape[:2]
        J = np.einsum("plj,nlk->npjlk", w, nD).reshape(len(idx) * w.shape[0] * 3, n_led * k)
        sc = np.maximum(np.sqrt(np.einsum("ij,ij->j", J, J)), 1e-300)
        Js = J / sc
        G = Js.T @ Js
        G[np.diag_indices_from(G)] += self.geometry_ridge * max(float(np.trace(G)) / len(G), 1e-300)
        return (np.linalg.solve(G, Js.T @ r) / sc).reshape(n_led, k)

    def lights_at(self, rows, cols, shape):
        w = self.drive * self.brightness[:, None, None] * self.gains[None]  # (P, L, 3)
        return np.einsum("plj,lnk->npjk", w, self.V[:, rows, cols]).reshape(len(rows), -1, 3)

    def light_field(self, shape):
        return light_matrices(self.V.astype(np.float32), self.drive, self.brightness, gains=self.gains).astype(np.float32)

    def to_arrays(self) -> dict[str, np.ndarray]:
        out = {"gains": self.gains.astype(np.float32)}
        if self.theta is not None:
            out["geometry_correction"] = self.theta.astype(np.float32)  # (L, 5): led_geometry.GEOMETRY_PARAMS
        return out


#: Largest condition number of a (column-scaled) Gram matrix solved on its Cholesky factor: the
#: solution's relative error grows with it (``cond(A)^2 eps``), so 1e10 keeps about 6 digits;
#: beyond it :func:`nnls_tall` works on the rows themselves.
MAX_GRAM_CONDITION = 1e10


def nnls_on_gram(gram: np.ndarray, atb: np.ndarray, btb: float) -> tuple[np.ndarray, float] | None:
    """``nnls_tall(A, b)`` from ``A^T A``, ``A^T b`` and ``b^T b`` alone, or None when ``A^T A`` is
    not positive definite or its condition number exceeds :data:`MAX_GRAM_CONDITION`.

    With the Cholesky factor ``A^T A = R^T R``, ``|A x - b|^2 = |R x - R^{-T} A^T b|^2 + (b^T b -
    |R^{-T} A^T b|^2)``: the same reduction as :func:`nnls_tall`, for a caller who can build the
    Gram matrix without the rows (the traced model's gains: P times fewer operations, P the patterns).

    Examples
    --------
    >>> rng = np.random.default_rng(2)
    >>> A = rng.random((400, 5)); b = A @ np.array([1.0, 0.0, 2.0, 0.5, 0.1]) - 0.3 * A[:, 1]
    >>> x, r = nnls_on_gram(A.T @ A, A.T @ b, float(b @ b)); x0, r0 = nnls_tall(A, b)
    >>> bool(np.allclose(x, x0, atol=1e-8)), bool(abs(r - r0) < 1e-6)
    (True, True)
    >>> nnls_on_gram(np.ones((2, 2)), np.ones(2), 2.0) is None  # singular: no answer from the Gram matrix
    True
    """
    from scipy.linalg import solve_triangular
    from scipy.optimize import nnls

    gram, atb = np.asarray(gram, np.float64), np.asarray(atb, np.float64)
    n = len(atb)
    if gram.shape != (n, n):
        raise ValueError(f"nnls_on_gram: gram must be ({n}, {n}) like atb, got {gram.shape}")
    if n == 0:
        return np.zeros(0), float(np.sqrt(max(btb, 0.0)))
    if not np.all(np.isfinite(gram)) or np.linalg.cond(gram) > MAX_GRAM_CONDITION:  # an SVD of n x n: cheap
        return None
    try:
        L = np.linalg.cholesky(gram)
    except np.linalg.LinAlgError:
        return None
    qb = solve_triangular(L, atb, lower=True)
    x, rn_small = nnls(L.T, qb, maxiter=50 * n)
    return x, float(np.sqrt(rn_small ** 2 + max(btb - float(qb @ qb), 0.0)))


def nnls_tall(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """``scipy.optimize.nnls`` for a tall ``A (m, n)``, solved on its triangular QR factor.

    With ``A = Q R`` (reduced), ``|A x - b|^2 = |R x - Q^T b|^2 + (|b|^2 - |Q^T b|^2)`` for
    every ``x``, so the constrained minimiser is the same while NNLS iterates on an ``n x n``
    system instead of ``m x n`` (m is pixels x patterns, n the LEDs: 30x to 1000x faster).
    ``R``, ``Q^T b`` and the second term come from one QR of ``[A | b]`` without forming ``Q``
    (its last diagonal entry is the distance of ``b`` from the column space): as stable as
    the full factorisation and 3.4x faster at 48000 x 24 (10 against 35 ms), where the
    Cholesky factor of ``A^T A`` would square ``A``'s condition number.

    Parameters
    ----------
    A : ndarray, shape (m, n)
    b : ndarray, shape (m,)

    Returns
    -------
    x : ndarray, shape (n,)
        The non-negative least-squares solution.
    rnorm : float
        ``|A x - b|`` of the original problem.

    Examples
    --------
    >>> from scipy.optimize import nnls
    >>> rng = np.random.default_rng(1)
    >>> A = rng.random((500, 6)); b = A @ np.array([1.0, 0.0, 2.0, 0.5, 0.0, 3.0]) - 0.4 * A[:, 1] + rng.normal(0, 0.01, 500)
    >>> x, r = nnls_tall(A, b); x0, r0 = nnls(A, b)
    >>> bool(np.allclose(x, x0, atol=1e-9)), round(r / r0, 9), bool(x.min() >= 0)
    (True, 1.0, True)
    """
    # Imported here, not at the top: scipy.optimize takes ~0.14 s to import, and loading a
    # calibration (every live start) imports this module without fitting (docs/live.md).
    from scipy.optimize import nnls

    A, b = np.asarray(A, np.float64), np.asarray(b, np.float64)
    if A.ndim != 2 or b.shape != (A.shape[0],):
        raise ValueError(f"nnls_tall: A must be (m, n) and b (m,), got {A.shape} and {b.shape}")
    m, n = A.shape
    if m <= 2 * n:
        x, rn = nnls(A, b, maxiter=50 * n)
        return x, float(rn)
    R = np.linalg.qr(np.column_stack([A, b]), mode="r")  # (n + 1, n + 1), upper triangular
    x, rn_small = nnls(R[:n, :n], R[:n, n], maxiter=50 * n)
    return x, float(np.hypot(rn_small, R[n, n]))
