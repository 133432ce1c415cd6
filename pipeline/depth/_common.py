"""Shared pieces of the integrators: the result type, normals -> pixel gradients, anchoring.

Discretisation (shared by all four integrators, so they agree on a plane and on each other):
heights live at pixel centres; a gradient sampled at two neighbouring pixels is averaged to
their midpoint, and ``h[j+1] - h[j] = (g[j] + g[j+1]) / 2`` is the equation of that edge.
Least squares over the edges gives the 5-point Poisson equation ``lap h = div g``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.base.frames import gradients_to_pixel_steps, normals_to_gradients

__all__ = ["DepthResult", "pixel_gradients", "half_pixel_gradients", "anchor_to_border", "check_mask"]


@dataclass
class DepthResult:
    """A height map and where it is trustworthy.

    Attributes
    ----------
    height : ndarray, shape (H, W), float32
        Heights in mm, positive toward the camera (reconstruction ``z``, see :mod:`pipeline.base.frames`).
        Finite everywhere; 0 outside ``mask`` for the masked integrator.
    mask : ndarray, shape (H, W), bool
        Pixels whose height comes from valid normals.
    meta : dict
        Integrator name and parameters (iterations for CG).
    """

    height: np.ndarray
    mask: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)


def check_mask(mask, shape: tuple[int, int], name: str) -> np.ndarray:
    """Boolean ``(H, W)`` mask (all True when None)."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise ValueError(f"{name}: mask must have shape {tuple(shape)}, got {m.shape}")
    return m.astype(bool)


def pixel_gradients(normals, mask, mm_per_px: float, max_slope: float, name: str):
    """Height differences per pixel step from unit normals.

    Parameters
    ----------
    normals : ndarray, shape (H, W, 3)
        Reconstruction-frame unit normals.
    mask : ndarray, shape (H, W), bool or None
        Invalid pixels (and non-finite normals) get zero gradient: the flat gel.
    mm_per_px : float
    max_slope : float
        Slopes are clipped to this magnitude (mm/mm) so grazing normals stay finite.

    Returns
    -------
    gc, gr : ndarray, shape (H, W), float32 for float32 normals, else float64
        ``dh/dcol`` and ``dh/drow`` in mm per pixel (:func:`pipeline.base.frames.gradients_to_pixel_steps`).
    mask : ndarray, shape (H, W), bool
        The input mask and-ed with finiteness.

    Examples
    --------
    >>> n = np.zeros((1, 1, 3)); n[..., 0] = -0.6; n[..., 2] = 0.8   # slope +0.75 along +x
    >>> gc, gr, m = pixel_gradients(n, None, 0.1, 20.0, "demo")
    >>> round(float(gc[0, 0]), 6), float(gr[0, 0]), bool(m[0, 0])
    (0.075, 0.0, True)
    """
    n = np.asarray(normals)
    if n.ndim != 3 or n.shape[-1] != 3 or min(n.shape) < 1:
        raise ValueError(f"{name}: normals must have shape (H, W, 3), got {n.shape}")
    if not (np.isfinite(mm_per_px) and mm_per_px > 0):
        raise ValueError(f"{name}: mm_per_px must be a positive number, got {mm_per_px!r}")
    # float32 normals (the solvers' default) are integrated in float32: half the memory
    # traffic, and float32 FFTs are ~2x faster; float64 normals keep the float64 reference.
    dt = np.float32 if n.dtype == np.float32 else np.float64
    nz = n[..., 2].astype(dt)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        m = check_mask(mask, n.shape[:2], name) & (nz > 0) & (nz < np.inf)  # False for NaN too
        # Invalid pixels become the flat gel's normal before the frames' n -> (p, q).
        p, q = normals_to_gradients(np.where(m[..., None], n, np.array([0.0, 0.0, 1.0], dt)), min_nz=0.0, dtype=dt)
        m &= np.isfinite(p) & np.isfinite(q)
    p = np.where(m, p, dt(0.0))
    q = np.where(m, q, dt(0.0))
    # Clip slopes (grazing normals) only where needed: the magnitude test is cheap.
    if np.abs(p).max() > max_slope / 1.5 or np.abs(q).max() > max_slope / 1.5:
        mag = np.hypot(p, q)
        with np.errstate(over="ignore", divide="ignore"):
            scale = np.where(mag > max_slope, max_slope / np.maximum(mag, np.finfo(dt).tiny), 1.0).astype(dt)
        p, q = p * scale, q * scale
    return (*gradients_to_pixel_steps(p, q, mm_per_px), m)


def half_pixel_gradients(gc, gr):
    """Edge gradients: ``(H, W-1)`` between columns and ``(H-1, W)`` between rows."""
    return 0.5 * (gc[:, 1:] + gc[:, :-1]), 0.5 * (gr[1:, :] + gr[:-1, :])


def divergence_neumann(gc, gr):
    """``div g`` ``(H, W)`` of the edge gradients with no flux through the image border."""
    ec, er = half_pixel_gradients(gc, gr)
    H, W = gc.shape
    f = np.zeros((H, W), dtype=gc.dtype)
    f[:, :-1] += ec
    f[:, 1:] -= ec
    f[:-1, :] += er
    f[1:, :] -= er
    return f


def anchor_to_border(h, mask):
    """Shift ``h`` so the median height of valid pixels on the image border is zero.

    The gel is flat away from contact, so the border is the natural zero. When no border
    pixel is valid (an object inside the frame, solved on its mask) the valid region's own
    rim is used: the valid pixels with an invalid 4-neighbour (an object resting on a table
    meets it at height 0 along its silhouette).
    """
    border = np.zeros(h.shape, dtype=bool)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    ref = mask & border
    if not ref.any():
        p = np.pad(mask, 1)
        ref = mask & ~(p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:])
    if not ref.any():
        ref = mask
    if not ref.any():
        return h
    return h - np.median(h[ref])
