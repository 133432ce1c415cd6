"""Near-field polynomial model: light vectors that vary smoothly over the image.

Each pattern-channel's light vector is a 2-D polynomial of total degree ``degree`` in the
normalised pixel position ``(u, v) in [-1, 1]^2`` (``(d + 1)(d + 2) / 2`` coefficients per
component; GelSight's commercial calibration uses degree 2), with uniform albedo:
``I_m(x) = n(x) . sum_t phi_t(x) C_mt``. The fit is linear least squares over contact and
flat samples; samples in attached shadow under the current fit are dropped and the fit
repeated.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.models.base import LightFieldModel
from calibration.samples import Samples

__all__ = ["NearFieldModel", "poly_terms"]


def poly_terms(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int], degree: int) -> np.ndarray:
    """Monomials ``u^i v^j`` (``i + j <= degree``) at the pixels, shape ``(N, T)``.

    Examples
    --------
    >>> poly_terms(np.array([0]), np.array([0]), (3, 3), 1).tolist()
    [[1.0, -1.0, -1.0]]
    """
    h, w = shape
    u = (np.asarray(cols, float) - (w - 1) / 2.0) / max((w - 1) / 2.0, 1.0)
    v = (np.asarray(rows, float) - (h - 1) / 2.0) / max((h - 1) / 2.0, 1.0)
    return np.stack([u ** i * v ** (d - i) for d in range(degree + 1) for i in range(d, -1, -1)], axis=-1)


class NearFieldModel(LightFieldModel):
    """Polynomial light field; ``coef`` has shape ``(P, C, T, 3)`` after :meth:`fit`."""

    name = "near"

    def __init__(self, degree: int = 2, shadow_passes: int = 2):
        if degree < 0:
            raise ValueError(f"NearFieldModel: degree must be >= 0, got {degree}")
        self.degree = degree
        self.shadow_passes = shadow_passes
        self.coef: np.ndarray | None = None
        self.flat = None

    def fit(self, samples: Samples, reference: np.ndarray | None = None) -> dict[str, Any]:
        _, p, c = samples.intensities.shape
        obs = samples.flat_observations.astype(np.float64)
        phi = poly_terms(samples.rows, samples.cols, samples.shape, self.degree)  # (N, T)
        X = (phi[:, :, None] * samples.normals[:, None, :]).reshape(len(samples), -1)  # (N, 3T)
        use = np.ones(obs.shape, dtype=bool)
        coef = np.zeros((obs.shape[1], X.shape[1]))
        for it in range(self.shadow_passes + 1):
            if use.all():
                coef = np.linalg.lstsq(X, obs, rcond=None)[0].T
            else:
                for m in range(obs.shape[1]):
                    coef[m] = np.linalg.lstsq(X[use[:, m]], obs[use[:, m], m], rcond=None)[0]
            if it < self.shadow_passes:
                use = (X @ coef.T) > 0.02 * np.abs(obs).max(axis=0)
        self.coef = coef.reshape(p, c, -1, 3)
        self.num_patterns, self.num_channels = p, c
        return self._fit_report(samples)

    def lights_at(self, rows, cols, shape):
        phi = poly_terms(rows, cols, shape, self.degree)
        return np.einsum("nt,mtk->nmk", phi, self.coef.reshape(-1, self.coef.shape[2], 3))

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"coef": self.coef.astype(np.float32), "degree": np.asarray(self.degree)}
