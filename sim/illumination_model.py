"""The per-pixel illumination model every later stage consumes.

``IlluminationModel`` is the contract between the ray tracer / calibration (which produce it)
and the renderer / normal solvers (which consume it). Per ``docs/design.md``, camera channel ``j`` of
pattern ``p`` sees

    I_pj(x) = mu * sum_i sigma_i W_p[i, j] * rho_j(x) / pi * max(0, n(x) . V_i(x))

and the solver's per-pixel light matrix is ``L_pj(x) = mu * sum_i sigma_i W_p[i, j] V_i(x)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["IlluminationModel", "light_matrices"]


@dataclass
class IlluminationModel:
    """Vector irradiance of every LED at every pixel.

    Attributes
    ----------
    V : ndarray, shape (L, H, W, 3), float32
        Reconstruction-frame vector irradiance per LED and pixel, per unit drive (W/mm^2).
    mm_per_px : float
        Pixel pitch on the gel.
    led_positions : ndarray, shape (L, 3)
        LED positions in the optical frame (mm); used for cast shadows.
    gel_z : float
        Optical ``z`` of the undeformed gel (mm).
    depth_heights : ndarray, shape (D,), optional
        Gel heights (mm, toward the camera) at which ``V_depth`` was sampled.
    V_depth : ndarray, shape (D, L, H, W, 3), optional
        The field at those heights (depth-dependent light field effect).
    directions : ndarray, shape (L, 3), optional
        Far-field (directional) lights: the unit direction toward each light, reconstruction
        frame (:func:`sim.far_field.far_field_illumination`). ``V`` is then the same at every
        pixel, and cast shadows are traced along these directions instead of toward
        ``led_positions``.
    meta : dict
        Provenance: scene name, rays, sampler, effects, ...
    """

    V: np.ndarray
    mm_per_px: float
    led_positions: np.ndarray
    gel_z: float
    depth_heights: np.ndarray | None = None
    V_depth: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    directions: np.ndarray | None = None

    def __post_init__(self):
        V = np.asarray(self.V)
        if V.ndim != 4 or V.shape[-1] != 3:
            raise ValueError(f"IlluminationModel: V must have shape (L, H, W, 3), got {V.shape}")
        pos = np.asarray(self.led_positions)
        if pos.shape != (V.shape[0], 3):
            raise ValueError(
                f"IlluminationModel: led_positions must have shape ({V.shape[0]}, 3), got {pos.shape}")
        if not np.all(np.isfinite(V)):
            raise ValueError("IlluminationModel: V contains NaN or Inf")
        if self.directions is not None:
            d = np.asarray(self.directions, dtype=np.float64)
            if d.shape != (V.shape[0], 3) or not np.all(np.isfinite(d)):
                raise ValueError(f"IlluminationModel: directions must be finite with shape ({V.shape[0]}, 3), "
                                 f"got {d.shape}")
            self.directions = d

    @property
    def shape(self) -> tuple[int, int]:
        """Image size ``(H, W)``."""
        return int(self.V.shape[1]), int(self.V.shape[2])

    @property
    def num_leds(self) -> int:
        return int(self.V.shape[0])


def light_matrices(V, drive, brightness=None, exposure: float = 1.0, gains=None):
    """Per-pixel light vectors of every pattern-channel.

    Parameters
    ----------
    V : ndarray, shape (L, H, W, 3)
        Vector irradiance per LED.
    drive : ndarray, shape (P, L, 3)
        RGB drive of each LED in each pattern (``W_p[i, j]``).
    brightness : ndarray, shape (P,), optional
        Global brightness per pattern (default 1).
    exposure : float
        Camera exposure ``mu``.
    gains : ndarray, shape (L,) or (L, 3), optional
        Per-LED (per-channel) brightness ``sigma_i``.

    Returns
    -------
    ndarray, shape (P, 3, H, W, 3)
        ``L_pj(x)``: for pattern ``p`` and camera channel ``j`` the light vector at each pixel.

    Examples
    --------
    >>> V = np.zeros((2, 1, 1, 3)); V[0, ..., 2] = 1.0; V[1, ..., 0] = 1.0
    >>> drive = np.zeros((1, 2, 3)); drive[0, 0, 0] = 1.0; drive[0, 1, 2] = 0.5
    >>> light_matrices(V, drive)[0, :, 0, 0].tolist()
    [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]
    """
    V = np.asarray(V)
    drive = np.asarray(drive, dtype=np.float64)
    if drive.ndim != 3 or drive.shape[1] != V.shape[0] or drive.shape[2] != 3:
        raise ValueError(f"light_matrices: drive must have shape (P, {V.shape[0]}, 3), got {drive.shape}")
    w = drive.copy()
    if brightness is not None:
        w = w * np.asarray(brightness, dtype=np.float64).reshape(-1, 1, 1)
    if gains is not None:
        g = np.asarray(gains, dtype=np.float64)
        w = w * (g.reshape(1, -1, 1) if g.ndim == 1 else g[None])
    out = exposure * np.einsum("plj,lhwk->pjhwk", w, V.astype(np.float64))
    return out.astype(V.dtype if V.dtype.kind == "f" else np.float32)
