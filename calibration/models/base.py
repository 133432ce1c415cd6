"""What every calibration model provides, and the per-pixel solve shared by light-field models.

A model is fitted on :class:`calibration.samples.Samples` and predicts normals for samples,
so that cross-validation treats every model alike. Light-field models (far-field,
near-field, traced) additionally export ``light_field(shape) -> (P, C, H, W, 3)`` such that
``I[p, :, :, c] ~ rho(x) * n(x) . light_field[p, c]`` (reconstruction frame), optionally with
``flat_field (P, C, H, W)`` by which observations are divided first (the far-field model's
albedo from the reference frames; ``None`` means 1).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.samples import Samples
from pipeline.base.errors import UserError

__all__ = ["CalibrationModel", "LightFieldModel", "solve_normals", "check_light_rank", "angular_error_deg"]


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between unit vectors ``a (..., 3)`` and ``b (..., 3)``.

    Examples
    --------
    >>> float(angular_error_deg(np.array([0.0, 0, 1]), np.array([1.0, 0, 0])))
    90.0
    """
    dot = np.clip(np.sum(np.asarray(a, float) * np.asarray(b, float), axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(dot))


def solve_normals(obs: np.ndarray, lights: np.ndarray, shadow_iterations: int = 2,
                  min_cond: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel least-squares Lambertian photometric stereo, with attached-shadow rejection.

    Parameters
    ----------
    obs : ndarray, shape (N, M)
        Observations (M = pattern-channels).
    lights : ndarray, shape (N, M, 3)
        Light vector of each observation.
    shadow_iterations : int
        After each solve, observations the current normal puts in attached shadow
        (``n . L <= 0``) are dropped and the pixel is solved again (while >= 3 remain).
    min_cond : float
        Pixels whose used light matrix has ``sigma_min / sigma_max`` below this are invalid.

    Returns
    -------
    normals : ndarray, shape (N, 3)
        Unit normals; ``(0, 0, 1)`` where invalid.
    albedo : ndarray, shape (N,)
    valid : ndarray, shape (N,), bool

    Examples
    --------
    >>> L = np.eye(3)[None] * 2.0
    >>> n, rho, ok = solve_normals(np.array([[0.0, 0.6, 0.8]]) * 2.0, L)
    >>> n.round(6).tolist(), rho.round(6).tolist(), ok.tolist()
    ([[0.0, 0.6, 0.8]], [1.0], [True])
    """
    obs = np.asarray(obs, dtype=np.float64)
    lights = np.asarray(lights, dtype=np.float64)
    if obs.ndim != 2 or lights.shape != obs.shape + (3,):
        raise ValueError(f"solve_normals: obs (N, M) and lights (N, M, 3) expected, got {obs.shape} and "
                         f"{lights.shape}")
    use = np.ones(obs.shape, dtype=bool)
    b = np.zeros((len(obs), 3))
    ok = np.zeros(len(obs), dtype=bool)
    for it in range(shadow_iterations + 1):
        Lw = lights * use[..., None]
        A = np.einsum("nmi,nmj->nij", Lw, Lw)
        rhs = np.einsum("nmi,nm->ni", Lw, obs)
        ev = np.linalg.eigvalsh(A)
        ok = (use.sum(1) >= 3) & (ev[:, 0] > (min_cond ** 2) * np.maximum(ev[:, 2], 1e-30))
        A[~ok] = np.eye(3)
        b = np.where(ok[:, None], np.linalg.solve(A, rhs[..., None])[..., 0], 0.0)
        if it == shadow_iterations:
            break
        lit = np.einsum("nmi,ni->nm", lights, b) > 0
        new_use = lit & (lit.sum(1, keepdims=True) >= 3) | ~(lit.sum(1, keepdims=True) >= 3)
        if np.array_equal(new_use, use):
            break
        use = new_use
    rho = np.linalg.norm(b, axis=1)
    ok &= rho > 0
    n = np.where(ok[:, None], b / np.maximum(rho, 1e-30)[:, None], np.array([0.0, 0.0, 1.0]))
    return n, rho, ok


def check_light_rank(samples: Samples, min_ratio: float = 0.05, what: str = "capture") -> float:
    """Raise :class:`UserError` unless the patterns give three independent light directions.

    Fits the linear far-field model ``I_m = a_m + n . L_m`` to the samples and compares the
    singular values of the stacked ``L (M, 3)``: with fewer than three independent light
    directions (e.g. only LEDs on one diameter of the ring, or fewer than three
    pattern-channels) normals are not determined and no model may be fitted silently.

    Returns the ratio ``sigma_3 / sigma_1``.
    """
    obs = samples.flat_observations.astype(np.float64)
    m = obs.shape[1]
    if m < 3:
        raise UserError(f"{what}: {m} pattern-channel(s) give fewer than three light directions; photometric "
                        "calibration needs at least three independent lights")
    A = np.concatenate([np.ones((len(samples), 1)), samples.normals], axis=1)
    coef = np.linalg.lstsq(A, obs, rcond=None)[0]  # (4, M)
    s = np.linalg.svd(coef[1:].T, compute_uv=False)
    ratio = float(s[-1] / max(s[0], 1e-30))
    if ratio < min_ratio:
        raise UserError(
            f"{what}: the lighting patterns span fewer than three independent light directions (singular values "
            f"of the fitted light matrix {np.round(s / max(s[0], 1e-30), 4).tolist()}, smallest/largest "
            f"{ratio:.4f} < {min_ratio}); use LEDs around the ring, not only on one diameter")
    return ratio


class CalibrationModel:
    """Base class: ``fit(samples) -> report``, ``predict(samples) -> (normals, valid)``."""

    name = "model"

    def fit(self, samples: Samples) -> dict[str, Any]:  # pragma: no cover - interface
        raise NotImplementedError

    def predict(self, samples: Samples) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - interface
        raise NotImplementedError

    def to_arrays(self) -> dict[str, np.ndarray]:  # pragma: no cover - interface
        raise NotImplementedError

    def _fit_report(self, samples: Samples) -> dict[str, Any]:
        n, ok = self.predict(samples.subset(samples.contact))
        err = angular_error_deg(n, samples.normals[samples.contact])[ok]
        return {"train_mean_angular_error_deg": float(err.mean()) if err.size else None,
                "train_samples": int(len(samples)), "train_valid_fraction": float(ok.mean()) if ok.size else 0.0}


class LightFieldModel(CalibrationModel):
    """A model that is a per-pixel light matrix; normals by :func:`solve_normals`."""

    flat: np.ndarray | None = None  # (P, C, H, W) flat field, or None

    def lights_at(self, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Light vectors ``(N, P * C, 3)`` at the given pixels."""
        raise NotImplementedError  # pragma: no cover - interface

    def light_field(self, shape: tuple[int, int]) -> np.ndarray:
        """Per-pixel light vectors ``(P, C, H, W, 3)`` float32 (the solvers' contract)."""
        h, w = shape
        rows, cols = np.mgrid[:h, :w]
        L = self.lights_at(rows.ravel(), cols.ravel(), shape)  # (HW, M, 3)
        p, c = self.num_patterns, self.num_channels
        return np.ascontiguousarray(L.reshape(h, w, p, c, 3).transpose(2, 3, 0, 1, 4)).astype(np.float32)

    def flat_field(self) -> np.ndarray | None:
        """``(P, C, H, W)`` divisor for observations before the solve, or None."""
        return self.flat

    def _observations(self, samples: Samples) -> np.ndarray:
        obs = samples.flat_observations.astype(np.float64)
        if self.flat is not None:
            f = self.flat.reshape(-1, *samples.shape)[:, samples.rows, samples.cols].T  # (N, M)
            obs = obs / np.maximum(f, 1e-6)
        return obs

    def predict(self, samples: Samples) -> tuple[np.ndarray, np.ndarray]:
        n, _, ok = solve_normals(self._observations(samples), self.lights_at(samples.rows, samples.cols, samples.shape))
        return n, ok
