"""Near-field polynomial model: light vectors that vary smoothly over the image.

Each pattern-channel's light vector is a 2-D polynomial of total degree ``degree`` in the
normalised pixel position ``(u, v) in [-1, 1]^2`` (``(d + 1)(d + 2) / 2`` coefficients per
component; GelSight's commercial calibration uses degree 2). The fit is linear least squares
over contact and flat samples; samples in attached shadow under the current fit are dropped
and the fit repeated.

What the polynomial describes (``flat``): with ``flat=True`` (default) the observations are
first divided by the flat field, the no-contact reference over its channel's median level
(as the far-field model does), so ``I_m(x) / flat_m(x) = n(x) . sum_t phi_t(x) C_mt``: the
reference measures albedo times irradiance at every pixel, whatever its spatial detail
(vignetting, an LED's hot spot, a printed pattern), and the polynomial only has to follow how
the light's *direction* and relative strength vary. With ``flat=False`` the albedo is uniform
and the polynomial has to follow the irradiance itself: ``I_m(x) = n(x) . sum_t phi_t(x) C_mt``.
Measured (presses 0-19 calibrate, 20-29 test; CV / test deg / test ball radius): on the
randomised virtual sensor of seed 0 (640 x 480, vignetting) uniform albedo read the darkened
corners as tilts, the depth maps rose 0.2-0.6 mm on flat gel and the ball fit locked onto those
false bumps, 5.33 / 4.20 / 169 %; flat-normalised 4.32 / 3.85 / 2.8 %. DIGIT: 19.7 / 19.1 /
1132 % -> 10.3 / 10.5 / 12.6 %. Shared GelSight: 8.13 / 7.26 / 2.4 % -> 7.38 / 5.82 / 3.4 %.
Samples whose flat field is below :data:`calibration.models.base.MIN_FLAT` are left out (and
get no normal).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.models.base import MIN_FLAT, LightFieldModel, flat_field
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
    """Polynomial light field; ``coef`` has shape ``(P, C, T, 3)`` after :meth:`fit`.

    Parameters
    ----------
    degree : int
        Total degree of the polynomial in the pixel position.
    shadow_passes : int
    flat : bool
        Divide the observations by the reference's flat field first (module docstring); the
        reference must then be given to :meth:`fit`.
    """

    name = "near"

    def __init__(self, degree: int = 2, shadow_passes: int = 2, flat: bool = True):
        if degree < 0:
            raise ValueError(f"NearFieldModel: degree must be >= 0, got {degree}")
        self.degree = degree
        self.shadow_passes = shadow_passes
        self.use_flat = bool(flat)
        self.coef: np.ndarray | None = None
        self.flat = None

    def fit(self, samples: Samples, reference: np.ndarray | None = None) -> dict[str, Any]:
        _, p, c = samples.intensities.shape
        self.flat = None
        if self.use_flat:
            if reference is None:
                raise ValueError("NearFieldModel.fit: flat=True needs the reference frames (P, H, W, C)")
            flat, _ = flat_field(reference, p, c, samples.shape)
            self.flat = flat.reshape(p, c, *samples.shape).astype(np.float32)
            fitted = samples.subset((flat[:, samples.rows, samples.cols] >= MIN_FLAT).all(axis=0))
        else:
            fitted = samples
        self._fit_field(fitted, p, c)
        return self._fit_report(samples)

    def _fit_field(self, samples: Samples, p: int, c: int) -> None:
        obs = self._observations(samples)  # divided by the flat field when there is one
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

    def lights_at(self, rows, cols, shape):
        phi = poly_terms(rows, cols, shape, self.degree)
        return np.einsum("nt,mtk->nmk", phi, self.coef.reshape(-1, self.coef.shape[2], 3))

    def to_arrays(self) -> dict[str, np.ndarray]:
        out = {"coef": self.coef.astype(np.float32), "degree": np.asarray(self.degree)}
        if self.flat is not None:
            out["flat_field"] = self.flat
        return out
