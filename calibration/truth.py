"""Ground truth on a sphere cap: heights and normals of a ball pressed into the gel.

A ball of radius ``R`` (mm) pressed into the gel leaves a contact disc of radius ``a < R``
(mm) in which the gel takes the ball's shape; outside the disc the gel is taken as flat.
Inside, at reconstruction-frame offset ``(dx, dy)`` from the disc centre (``d^2 = dx^2 +
dy^2``), the height is ``h = sqrt(R^2 - d^2) - sqrt(R^2 - a^2)`` (a bump toward the camera,
zero on the rim) and the gradients are ``dh/dx = -dx / sqrt(R^2 - d^2)`` (same for ``y``),
turned into normals by :func:`pipeline.base.frames.gradients_to_normals`. The cap is the one
the renderer presses, :func:`sim.geometry.shapes.sphere`, at the depth
:func:`sim.geometry.shapes.cap_depth` of the contact radius; the centre's pixel is mapped to
mm by :func:`pipeline.base.frames.pixel_to_recon`, so the signs follow the project's conventions.

Where the sphere stops being the truth. A pressed gel cannot follow the ball's edge: near the
rim its surface is the cap smoothed (the virtual sensor's ``rim_smoothing``, a Gaussian of
standard deviation ``sigma``), and there the cap's normals are wrong. Measured on the
randomised virtual sensors (seeds 0-3 of ``iristac bench calibration --sensors``, 30 presses
each, the presses inside the image; :func:`rim_error_profile`), the mean angle between the
cap's normals and the exact ones per band of distance inside the rim is 14.7 deg (median over
presses; 0-0.5 sigma), 8.1 (0.5-1), 3.7 (1-1.5), 1.3 (1.5-2), 0.27 (2-2.5) and under 0.2 deeper
in, never above 0.8 deg on any pixel beyond 2 sigma: :data:`SPHERE_TRUST_SIGMAS`. Where a
sensor's smoothing is unknown, the samples' rim margin
(:data:`calibration.samples.RIM_FRACTION`) stands in for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.base.frames import gradients_to_normals, pixel_to_recon
from sim.geometry.shapes import cap_depth, sphere

__all__ = ["SphereCap", "sphere_cap", "SPHERE_TRUST_SIGMAS", "sphere_trust_margin_px", "rim_error_profile"]

#: The sphere cap's normals are trusted from this many standard deviations of the gel's rim
#: smoothing inside the contact rim inward (measured: the module's docstring).
SPHERE_TRUST_SIGMAS = 2.0


@dataclass
class SphereCap:
    """Truth of one press.

    Attributes
    ----------
    height : ndarray, shape (H, W), float64
        mm, positive toward the camera; 0 outside the contact.
    normals : ndarray, shape (H, W, 3), float64
        Unit normals in the reconstruction frame; ``(0, 0, 1)`` outside the contact.
    gradients : ndarray, shape (H, W, 2), float64
        ``(dh/dx, dh/dy)`` in the reconstruction frame; 0 outside.
    contact : ndarray, shape (H, W), bool
        Pixels whose centre lies inside the contact disc.
    """

    height: np.ndarray
    normals: np.ndarray
    gradients: np.ndarray
    contact: np.ndarray


def sphere_cap(shape: tuple[int, int], center_rc: tuple[float, float], contact_radius_px: float,
               ball_radius_mm: float, mm_per_px: float) -> SphereCap:
    """Heights and normals of a ball of radius ``ball_radius_mm`` pressed at ``center_rc``.

    Parameters
    ----------
    shape : (H, W)
        Image size.
    center_rc : (row, col)
        Contact centre in pixels (may be fractional).
    contact_radius_px : float
        Contact disc radius in pixels; must be below the ball radius in pixels.
    ball_radius_mm, mm_per_px : float
        Ball radius and pixel pitch.

    Returns
    -------
    SphereCap

    Examples
    --------
    The normal on the rim leans away from the centre; the apex is the highest point:

    >>> cap = sphere_cap((9, 9), (4.0, 4.0), 3.0, 2.0, 0.5)
    >>> cap.normals[4, 4].round(6).tolist(), bool(cap.normals[4, 6, 0] > 0), bool(cap.normals[2, 4, 1] > 0)
    ([0.0, 0.0, 1.0], True, True)
    >>> round(float(cap.height[4, 4]), 6), round(2.0 - float(np.sqrt(4.0 - 1.5 ** 2)), 6)
    (0.677124, 0.677124)
    """
    h, w = int(shape[0]), int(shape[1])
    if ball_radius_mm <= 0 or mm_per_px <= 0:
        raise ValueError(f"sphere_cap: ball_radius_mm and mm_per_px must be > 0, got {ball_radius_mm}, {mm_per_px}")
    a_mm = float(contact_radius_px) * mm_per_px
    if not 0 <= a_mm < ball_radius_mm:
        raise ValueError(
            f"sphere_cap: contact radius {contact_radius_px} px = {a_mm:.4f} mm must be in [0, ball radius "
            f"{ball_radius_mm} mm)")
    x0, y0 = pixel_to_recon(center_rc[0], center_rc[1], (h, w), mm_per_px)
    if a_mm == 0:
        zero = np.zeros((h, w))
        return SphereCap(height=zero, normals=gradients_to_normals(zero, zero), gradients=np.zeros((h, w, 2)),
                         contact=np.zeros((h, w), bool))
    f = sphere((h, w), mm_per_px, ball_radius_mm, float(cap_depth(ball_radius_mm, a_mm)), center=(float(x0), float(y0)))
    return SphereCap(height=f.height, normals=gradients_to_normals(f.p, f.q), gradients=np.stack([f.p, f.q], axis=-1),
                     contact=f.contact)


def sphere_trust_margin_px(rim_smoothing_px: float) -> float:
    """The band inside the contact rim (pixels) where a gel smoothed by ``rim_smoothing_px``
    (Gaussian standard deviation) is not the sphere cap: :data:`SPHERE_TRUST_SIGMAS` of it.

    >>> sphere_trust_margin_px(3.0)
    6.0
    """
    if not rim_smoothing_px >= 0:
        raise ValueError(f"sphere_trust_margin_px: rim_smoothing_px must be >= 0, got {rim_smoothing_px}")
    return SPHERE_TRUST_SIGMAS * float(rim_smoothing_px)


def rim_error_profile(exact_normals: np.ndarray, center_rc: tuple[float, float], contact_radius_px: float,
                      ball_radius_mm: float, mm_per_px: float, band_px: float,
                      bands: int = 12) -> np.ndarray:
    """How far the sphere cap's normals are from exact ones, per band of distance inside the rim.

    Parameters
    ----------
    exact_normals : ndarray, shape (H, W, 3)
        The pressed gel's true normals (a virtual sensor's truth).
    center_rc, contact_radius_px, ball_radius_mm, mm_per_px
        The press, as :func:`sphere_cap` takes it.
    band_px : float
        Width of each band (e.g. half the rim smoothing's standard deviation).
    bands : int

    Returns
    -------
    ndarray, shape (bands,)
        Mean angle (degrees) in each band, band ``i`` covering ``[i, i + 1) * band_px``
        inside the rim; NaN for an empty band.

    Examples
    --------
    The cap against itself:

    >>> cap = sphere_cap((40, 40), (20.0, 20.0), 12.0, 2.0, 0.1)
    >>> round(float(np.nanmax(rim_error_profile(cap.normals, (20.0, 20.0), 12.0, 2.0, 0.1, 2.0, 4))), 4)
    0.0
    """
    n = np.asarray(exact_normals, np.float64)
    h, w = n.shape[:2]
    cap = sphere_cap((h, w), center_rc, contact_radius_px, ball_radius_mm, mm_per_px)
    cos = np.clip(np.sum(n * cap.normals, axis=-1) / np.maximum(np.linalg.norm(n, axis=-1), 1e-12), -1.0, 1.0)
    err = np.degrees(np.arccos(cos))
    rows, cols = np.mgrid[:h, :w]
    inside = contact_radius_px - np.hypot(rows - center_rc[0], cols - center_rc[1])
    out = np.full(int(bands), np.nan)
    for i in range(int(bands)):
        sel = (inside >= i * band_px) & (inside < (i + 1) * band_px)
        if sel.any():
            out[i] = float(err[sel].mean())
    return out
