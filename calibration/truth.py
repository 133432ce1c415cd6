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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.base.frames import gradients_to_normals, pixel_to_recon
from sim.geometry.shapes import cap_depth, sphere

__all__ = ["SphereCap", "sphere_cap"]


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
