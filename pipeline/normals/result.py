"""What every normal solver returns (:class:`NormalResult`; the torch solvers build it with
:func:`pipeline.normals._lstsq.finalize`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["NormalResult", "COND_CAP"]

#: The condition number an invalid or singular pixel reads (every output stays finite).
COND_CAP = 1e12


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
