"""Traced model: the ray tracer's fields ``V_i`` with fitted per-LED, per-channel gains.

With the true normals known on the cap, ``I_pj(x) = rho sum_i sigma_ij W_p[i, j] b_p
max(0, n(x) . V_i(x))`` is linear in the gains ``sigma_ij`` (``rho = 1``: the gel's albedo is
uniform; exposure and the ``1 / pi`` fold into ``sigma``), so they are fitted per camera
channel by non-negative least squares over all patterns. Any pattern, captured or not, then
has the light field ``sim.illumination_model.light_matrices(V, W, b, gains=sigma)``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.optimize import nnls

from calibration.models.base import LightFieldModel
from calibration.samples import Samples
from pipeline.errors import UserError
from sim.illumination_model import light_matrices

__all__ = ["TracedModel"]


class TracedModel(LightFieldModel):
    """Gains on given LED fields.

    Parameters
    ----------
    V : ndarray, shape (L, H, W, 3)
        Vector irradiance per LED (an ``IlluminationModel.V``).
    drive : ndarray, shape (P, L, 3)
    brightness : ndarray, shape (P,), optional
    """

    name = "traced"

    def __init__(self, V: np.ndarray, drive: np.ndarray, brightness: np.ndarray | None = None):
        V = np.asarray(V, dtype=np.float64)
        drive = np.asarray(drive, dtype=np.float64)
        if V.ndim != 4 or V.shape[-1] != 3:
            raise UserError(f"traced model: V must have shape (L, H, W, 3), got {V.shape}")
        if drive.ndim != 3 or drive.shape[1:] != (V.shape[0], 3):
            raise UserError(f"traced model: the capture's drive {drive.shape} does not match the illumination "
                            f"model's {V.shape[0]} LEDs (expected (P, {V.shape[0]}, 3))")
        self.V = V
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
        Vs = self.V[:, samples.rows, samples.cols]  # (L, N, 3)
        s = np.maximum(np.einsum("lnk,nk->nl", Vs, samples.normals), 0.0)  # (N, L)
        w = self.drive * self.brightness[:, None, None]  # (P, L, 3)
        gains = np.zeros((self.V.shape[0], 3))
        resid = []
        for j in range(3):
            A = (s[:, None, :] * w[None, :, :, j]).reshape(-1, self.V.shape[0])  # (N * P, L)
            b = samples.intensities[:, :, j].reshape(-1).astype(np.float64)
            active = np.abs(A).sum(0) > 0
            g = np.zeros(self.V.shape[0])
            # Column scaling keeps NNLS well conditioned (V is ~1e-4 W/mm^2).
            sc = np.maximum(np.abs(A[:, active]).max(0), 1e-300)
            g_act, rn = nnls(A[:, active] / sc, b, maxiter=50 * A.shape[1])
            g[active] = g_act / sc
            gains[:, j] = g
            resid.append(rn / np.sqrt(max(len(b), 1)))
        self.gains = gains
        rep = self._fit_report(samples)
        rep["residual_rms_dn"] = float(np.sqrt(np.mean(np.square(resid))))
        return rep

    def lights_at(self, rows, cols, shape):
        w = self.drive * self.brightness[:, None, None] * self.gains[None]  # (P, L, 3)
        return np.einsum("plj,lnk->npjk", w, self.V[:, rows, cols]).reshape(len(rows), -1, 3)

    def light_field(self, shape):
        return light_matrices(self.V.astype(np.float32), self.drive, self.brightness, gains=self.gains).astype(np.float32)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"gains": self.gains.astype(np.float32)}
