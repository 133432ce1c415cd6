"""Figures of merit of the imaging result on a flat gel (paper §IV-B and §V-2).

The one-source image is the flat-gel irradiance ``E_i`` (W/mm^2 per W emitted); a Lambertian
gel of albedo ``rho`` shows ``rho / pi * E``. Eq. (15) combines sources with RGB weights
``c_ij``, brightnesses ``sigma_i`` and exposure ``mu``: ``c_j = mu sum_i sigma_i E_i c_ij``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["pattern_image", "uniformity", "image_metrics"]

# Mean intensities are reported in W/m^2 per W of LED power (1 W/mm^2 = 1e6 W/m^2).
_W_PER_M2 = 1e6


def pattern_image(E, weights, brightness=None, exposure: float = 1.0) -> np.ndarray:
    """Eq. (15): the RGB image ``(H, W, 3)`` of per-source images ``E`` (L, H, W).

    Parameters
    ----------
    E : ndarray, shape (L, H, W)
    weights : ndarray, shape (L, 3)
        RGB weights ``c_ij`` of each source.
    brightness : ndarray, shape (L,), optional
        ``sigma_i`` (default 1).
    exposure : float
        ``mu``.

    Examples
    --------
    >>> E = np.ones((2, 1, 1)); w = np.array([[1.0, 0, 0], [0, 0, 2.0]])
    >>> pattern_image(E, w, exposure=0.5)[0, 0].tolist()
    [0.5, 0.0, 1.0]
    """
    E = np.asarray(E, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    if E.ndim != 3 or w.shape != (E.shape[0], 3):
        raise ValueError(f"pattern_image: expected E (L, H, W) and weights (L, 3), got {E.shape} and {w.shape}")
    if brightness is not None:
        w = w * np.asarray(brightness, dtype=np.float64).reshape(-1, 1)
    return exposure * np.einsum("lhw,lj->hwj", E, w)


def uniformity(img) -> dict:
    """Coefficient of variation and min/max of an image (over every pixel).

    Examples
    --------
    >>> u = uniformity(np.array([[1.0, 3.0]]))
    >>> round(u["cv"], 6), u["min_max"]
    (0.5, 0.3333333333333333)
    """
    img = np.asarray(img, dtype=np.float64)
    mean = float(img.mean())
    if mean <= 0:
        return {"mean": mean, "cv": 0.0, "min_max": 0.0}
    return {"mean": mean, "cv": float(img.std() / mean), "min_max": float(img.min() / img.max())}


def image_metrics(E, rgb, fraction) -> dict:
    """Flux fraction on screen, mean intensity and uniformity, overall and per channel.

    Parameters
    ----------
    E : ndarray, shape (L, H, W), or (3, L, H, W) per camera channel (dispersion effect)
        Per-source flat-gel irradiance on the screen.
    rgb : ndarray, shape (L, 3)
        Per-source RGB weights (the scene's ``leds.rgb``).
    fraction : array_like, shape (L,)
        Fraction of each source's power landing on the screen.

    Returns
    -------
    dict with ``fraction_on_screen``, ``mean_intensity`` (W/m^2 per W per LED, all LEDs lit),
    ``uniformity_cv``, ``min_max`` and ``channels`` (per R, G, B after channel separation).
    """
    E = np.asarray(E, dtype=np.float64)
    if E.ndim == 4:  # channel j sees the field traced with channel j's refractive index
        img = np.stack([pattern_image(E[j], rgb)[..., j] for j in range(3)], axis=2)
    else:
        img = pattern_image(E, rgb)
    white = img.mean(axis=2)
    u = uniformity(white)
    chans = {}
    for j, name in enumerate("RGB"):
        uj = uniformity(img[..., j])
        chans[name] = {"mean_intensity": uj["mean"] * _W_PER_M2, "uniformity_cv": uj["cv"], "min_max": uj["min_max"]}
    return {"fraction_on_screen": float(np.mean(fraction)), "mean_intensity": u["mean"] * _W_PER_M2,
            "uniformity_cv": u["cv"], "min_max": u["min_max"], "channels": chans}
