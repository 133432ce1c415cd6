"""Far-field model: one light vector per pattern-channel, albedo from the reference frames.

With a reference (flat, ``n = z``) frame ``I_ref,m(x) = rho_m(x) L_m,z`` the ratio
``I_m / I_ref,m = n . (L_m / L_m,z)`` no longer depends on the albedo, and is linear in the two
unknowns ``L_m,x / L_m,z`` and ``L_m,y / L_m,z``: ``I_m / I_ref,m - n_z = a_m n_x + b_m n_y``.
The scale ``s_m`` (median reference) makes ``L_m = s_m (a_m, b_m, 1)`` and the flat field
``I_ref,m(x) / s_m``, so that ``I_m / flat_m = n . L_m``. Samples in attached shadow under
the current fit (``n . L_m <= 0``) are dropped and the fit repeated.

Where the reference is dark (a printed marker, a corner the vignetting blacks out, a channel
whose light does not reach) the ratio is undefined: a reference of 0 DN made one sample's ratio
~1e7, the least-squares light vectors came out ~1e6 times too long and every prediction of the
randomised virtual sensors was invalid (``iristac bench calibration --sensors``: "far 90 deg").
So samples whose reference is below :data:`calibration.models.base.MIN_FLAT` of the channel's
median level are left out of the fit, and pixels whose flat field is below it have no normal
(invalid; :class:`calibration.models.base.LightFieldModel`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.models.base import MIN_FLAT, LightFieldModel, flat_field
from calibration.samples import Samples

__all__ = ["FarFieldModel"]


class FarFieldModel(LightFieldModel):
    """One light vector per pattern-channel.

    Attributes (after :meth:`fit`)
    ------------------------------
    lights : ndarray, shape (P, C, 3)
    flat : ndarray, shape (P, C, H, W)
    """

    name = "far"

    def __init__(self, shadow_passes: int = 2):
        self.shadow_passes = shadow_passes
        self.lights: np.ndarray | None = None
        self.flat = None

    def fit(self, samples: Samples, reference: np.ndarray | None = None) -> dict[str, Any]:
        """Fit on ``samples``; ``reference (P, H, W, C)`` gives the flat field."""
        if reference is None:
            raise ValueError("FarFieldModel.fit: the reference frames (P, H, W, C) are needed for the flat field")
        _, p, c = samples.intensities.shape
        flat, scale = flat_field(reference, p, c, samples.shape)  # (M, H, W), (M,)
        obs = samples.flat_observations.astype(np.float64)
        ref = samples.reference.reshape(len(samples), -1).astype(np.float64)
        ratio = obs / np.maximum(ref, 1e-6)
        n = samples.normals
        lit = ref >= MIN_FLAT * scale  # a dark reference leaves the ratio undefined (module docstring)
        use = lit.copy()
        ab = np.zeros((obs.shape[1], 2))
        for _ in range(self.shadow_passes + 1):
            for m in range(obs.shape[1]):
                u = use[:, m]
                ab[m] = np.linalg.lstsq(n[u, :2], ratio[u, m] - n[u, 2], rcond=None)[0]
            shade = n[:, :2] @ ab.T + n[:, 2:3]  # (N, M) = n . (a, b, 1)
            use = (shade > 0.02) & lit
        self.lights = (np.concatenate([ab, np.ones((len(ab), 1))], axis=1) * scale[:, None]).reshape(p, c, 3)
        self.flat = flat.reshape(p, c, *samples.shape).astype(np.float32)
        self.num_patterns, self.num_channels = p, c
        return self._fit_report(samples)

    def lights_at(self, rows, cols, shape):
        return np.broadcast_to(self.lights.reshape(1, -1, 3), (len(rows), self.lights.shape[0] * self.lights.shape[1], 3))

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"lights": self.lights.astype(np.float32), "flat_field": self.flat}
