"""Ratio to the no-contact reference frame: cancels albedo and vignetting.

The reference frame shows the flat gel (``n0 = (0, 0, 1)``) under the same pattern, so
``ref_k(x) = rho(x) L_k(x) . n0 = rho(x) L_kz(x)``. Dividing, ``I_k / ref_k = n . L_k / L_kz``:
the albedo and any per-pixel gain (vignetting, LED brightness) cancel, and the solvers run
unchanged on the ratios with light vectors ``L_k / L_kz``. The albedo they return is then
relative to the reference (1 where the gel is unchanged).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ratio_to_reference"]


def ratio_to_reference(observations, reference, lights, *, min_reference: float = 1.0):
    """Observations and lights divided through by the reference frame.

    Parameters
    ----------
    observations : ndarray, shape (N_obs, H, W)
        Dark-subtracted intensities of the contact frame.
    reference : ndarray, shape (N_obs, H, W)
        Dark-subtracted intensities of the no-contact frame under the same pattern-channels.
    lights : ndarray, shape (N_obs, 3) or (N_obs, H, W, 3)
        Light vectors; each must have ``L_z > 0`` (it lights the flat gel).
    min_reference : float
        Reference values at or below this are too dark to divide by: those observations
        become NaN, which every solver ignores (masking the pixel if fewer than three remain).

    Returns
    -------
    ratios : ndarray, shape (N_obs, H, W), float64
    lights : ndarray, same shape as ``lights``, float64
        ``L / L_z`` (observations with ``L_z <= 0`` are NaN in ``ratios``).

    Examples
    --------
    >>> L = np.array([[0.0, 0, 2.0], [1.0, 0, 2.0], [0, 1.0, 2.0]])
    >>> ref = np.full((3, 1, 1), 40.0)                 # albedo 20
    >>> n = np.array([0.6, 0.0, 0.8])
    >>> img = (20 * L @ n)[:, None, None]
    >>> r, Lr = ratio_to_reference(img, ref, L)
    >>> np.round(r[:, 0, 0], 3).tolist(), Lr[1].tolist()
    ([0.8, 1.1, 0.8], [0.5, 0.0, 1.0])
    """
    obs = np.asarray(observations, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    L = np.asarray(lights, dtype=np.float64)
    if obs.ndim != 3:
        raise ValueError(f"ratio_to_reference: observations must have shape (N_obs, H, W), got {obs.shape}")
    if ref.shape != obs.shape:
        raise ValueError(f"ratio_to_reference: reference must have shape {obs.shape}, got {ref.shape}")
    if not (L.shape == (obs.shape[0], 3) or L.shape == obs.shape + (3,)):
        raise ValueError(f"ratio_to_reference: lights must have shape ({obs.shape[0]}, 3) or "
                         f"{obs.shape + (3,)}, got {L.shape}")
    lz = L[..., 2]
    lz_ok = np.isfinite(lz) & (lz > 0)
    Lr = np.where(lz_ok[..., None], L / np.where(lz_ok, lz, 1.0)[..., None], 0.0)
    lz_b = lz_ok[:, None, None] if L.ndim == 2 else lz_ok
    ok = np.isfinite(ref) & (ref > min_reference) & lz_b
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = np.where(ok, obs / np.where(ok, ref, 1.0), np.nan)
    return ratios, Lr
