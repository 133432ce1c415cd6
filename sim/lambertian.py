"""The core image-formation formula (``docs/design.md``, "Physics"), without any camera effects.

    I_pj(x) = mu * sum_i sigma_i W_p[i, j] * rho_j(x) / pi * max(0, n(x) . V_i(x))

The renderer (:mod:`sim.render`) adds the camera effects around this; calibration and tests
use it directly as the noiseless truth.
"""

from __future__ import annotations

import numpy as np

__all__ = ["shade"]


def shade(V, normals, albedo, drive, brightness=None, exposure: float = 1.0, gains=None,
          attached_shadows: bool = True):
    """Noiseless Lambertian image of a surface under each pattern.

    Parameters
    ----------
    V : ndarray, shape (L, H, W, 3)
        Reconstruction-frame vector irradiance per LED (see :class:`sim.illumination_model.IlluminationModel`).
    normals : ndarray, shape (H, W, 3)
        Unit surface normals, reconstruction frame.
    albedo : float or ndarray, shape (H, W) or (H, W, 3)
        Lambertian albedo per camera channel ``rho_j``.
    drive : ndarray, shape (P, L, 3)
        RGB drive ``W_p[i, j]`` of each LED in each pattern.
    brightness : ndarray, shape (P,), optional
        Global brightness per pattern.
    exposure : float
        ``mu``.
    gains : ndarray, shape (L,) or (L, 3), optional
        Per-LED (per-channel) brightness ``sigma_i``.
    attached_shadows : bool
        Apply ``max(0, .)`` per LED (True, physical). False gives the linear model that
        least-squares photometric stereo assumes.

    Returns
    -------
    ndarray, shape (P, H, W, 3), float64
        Radiance per pattern and camera channel.

    Examples
    --------
    A flat white gel under one LED straight above it with ``|V| = pi``:

    >>> V = np.zeros((1, 1, 1, 3)); V[..., 2] = np.pi
    >>> n = np.array([[[0.0, 0.0, 1.0]]])
    >>> shade(V, n, 1.0, np.ones((1, 1, 3)))[0, 0, 0].tolist()
    [1.0, 1.0, 1.0]
    """
    V = np.asarray(V, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if V.ndim != 4 or V.shape[-1] != 3:
        raise ValueError(f"shade: V must have shape (L, H, W, 3), got {V.shape}")
    if normals.shape != V.shape[1:]:
        raise ValueError(f"shade: normals must have shape {V.shape[1:]}, got {normals.shape}")
    drive = np.asarray(drive, dtype=np.float64)
    if drive.ndim != 3 or drive.shape[1:] != (V.shape[0], 3):
        raise ValueError(f"shade: drive must have shape (P, {V.shape[0]}, 3), got {drive.shape}")
    w = drive
    if brightness is not None:
        w = w * np.asarray(brightness, dtype=np.float64).reshape(-1, 1, 1)
    if gains is not None:
        g = np.asarray(gains, dtype=np.float64)
        w = w * (g.reshape(1, -1, 1) if g.ndim == 1 else g[None])
    s = np.einsum("lhwk,hwk->lhw", V, normals)  # n . V_i per LED
    if attached_shadows:
        s = np.maximum(s, 0.0)
    img = np.einsum("plj,lhw->phwj", w, s)
    rho = np.asarray(albedo, dtype=np.float64)
    if rho.ndim == 2:
        rho = rho[..., None]
    return exposure * img * rho / np.pi
