"""Closed-form near-field light of bare LEDs (no lens): the reference the ray tracer must match.

An LED at ``S`` with unit axis ``D`` radiates intensity ``I(theta) = I0 cos^m(theta)`` inside
a cone of half-angle ``theta_c`` about ``D`` and nothing outside it. ``I0`` is chosen so that
each LED emits unit power (1 W per unit drive):

    Phi = I0 * 2 pi (1 - cos^(m+1) theta_c) / (m + 1) = 1.

At a gel point ``X`` the vector irradiance is ``V = I(theta) / |S - X|^2 * l`` with
``l = (S - X) / |S - X|`` the unit vector toward the LED. A surface with unit normal ``n``
receives irradiance ``max(0, n . V)`` (W / mm^2). This is the Quéau et al. near-field model
with ``mu = m``; positions are in the optical frame, the returned vectors in the
reconstruction frame (see :mod:`pipeline.base.frames`).
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.base.frames import optical_to_recon, pixel_to_optical

__all__ = ["ring_geometry", "led_intensity_scale", "point_source_field"]


def ring_geometry(count: int = 24, radius: float = 40.0, height: float = 0.0, tilt_deg: float = 0.0,
                  phase_deg: float = 0.0):
    """Positions ``(L, 3)`` and unit axes ``(L, 3)`` of a ring of LEDs in the optical frame.

    LED ``i`` sits at azimuth ``phase + 360 i / count`` degrees (LED 0 on ``+x`` by default),
    at ``z = height``, facing ``+z`` and tilted by ``tilt_deg`` toward the axis.

    Examples
    --------
    >>> pos, axes = ring_geometry(4, 10.0)
    >>> np.round(pos[1], 6).tolist(), np.abs(axes[0]).tolist()
    ([0.0, 10.0, 0.0], [0.0, 0.0, 1.0])
    """
    if count < 1:
        raise ValueError(f"ring_geometry: count must be >= 1, got {count}")
    phi = np.deg2rad(phase_deg + 360.0 * np.arange(count) / count)
    pos = np.stack([radius * np.cos(phi), radius * np.sin(phi), np.full(count, float(height))], axis=-1)
    t = math.radians(tilt_deg)
    # Tilt toward the axis: the axis leans along -radial.
    axes = np.stack([-math.sin(t) * np.cos(phi), -math.sin(t) * np.sin(phi), np.full(count, math.cos(t))], axis=-1)
    return pos, axes


def led_intensity_scale(m: float, cone_half_angle_deg: float) -> float:
    """``I0`` (W/sr) of a ``cos^m`` emitter of unit power inside the given cone.

    Examples
    --------
    A Lambertian emitter over the full hemisphere has ``I0 = 1/pi``:

    >>> round(led_intensity_scale(1.0, 90.0) * math.pi, 12)
    1.0
    """
    c = math.cos(math.radians(cone_half_angle_deg))
    return (m + 1.0) / (2.0 * math.pi * (1.0 - c ** (m + 1.0)))


def point_source_field(positions, axes, shape, mm_per_px: float, gel_z: float, *, m: float = 1.0,
                       cone_half_angle_deg: float = 60.0, gel_height=None, dtype=np.float32):
    """Vector irradiance ``V`` of each LED at each pixel of the gel, no lens.

    Parameters
    ----------
    positions, axes : ndarray, shape (L, 3)
        LED positions (mm) and unit emission axes in the optical frame.
    shape : (H, W)
        Pixel grid of the camera; pixels map to the gel by :func:`pipeline.base.frames.pixel_to_optical`.
    mm_per_px : float
        Pixel pitch on the gel.
    gel_z : float
        Optical ``z`` of the undeformed gel surface (mm).
    m, cone_half_angle_deg : float
        Emission profile ``cos^m`` inside the cone.
    gel_height : ndarray, shape (H, W), optional
        Heights (mm, positive toward the camera, i.e. toward the LEDs) of a deformed gel; the
        field is then evaluated at the displaced surface points (depth-dependent light field).

    Returns
    -------
    V : ndarray, shape (L, H, W, 3)
        Reconstruction-frame vector irradiance (W/mm^2 per unit drive).

    Examples
    --------
    One Lambertian LED 10 mm straight below the centre pixel of a 1-pixel gel:

    >>> V = point_source_field(np.array([[0.0, 0, 0]]), np.array([[0.0, 0, 1]]), (1, 1), 1.0, 10.0,
    ...                        cone_half_angle_deg=90.0)
    >>> round(float(V[0, 0, 0, 2]) * math.pi * 100, 6)
    1.0
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    if positions.shape != axes.shape:
        raise ValueError(f"point_source_field: positions {positions.shape} and axes {axes.shape} differ")
    h, w = int(shape[0]), int(shape[1])
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    x, y = pixel_to_optical(rows, cols, (h, w), mm_per_px)
    z = np.full_like(x, float(gel_z))
    if gel_height is not None:
        gh = np.asarray(gel_height, dtype=np.float64)
        if gh.shape != (h, w):
            raise ValueError(f"point_source_field: gel_height must have shape {(h, w)}, got {gh.shape}")
        z = z - gh  # positive height moves the surface toward the camera (optical -z)
    X = np.stack([x, y, z], axis=-1)  # (H, W, 3) optical
    i0 = led_intensity_scale(m, cone_half_angle_deg)
    cos_c = math.cos(math.radians(cone_half_angle_deg))
    out = np.empty((len(positions), h, w, 3), dtype=dtype)
    for k, (s, d) in enumerate(zip(positions, axes)):
        to_src = s - X
        dist2 = np.einsum("hwc,hwc->hw", to_src, to_src)
        dist = np.sqrt(dist2)
        l = to_src / dist[..., None]
        cos_t = np.einsum("hwc,c->hw", -l, d / np.linalg.norm(d))
        inside = cos_t >= cos_c - 1e-12
        inten = np.where(inside, i0 * np.clip(cos_t, 0.0, None) ** m, 0.0)
        out[k] = optical_to_recon(l * (inten / dist2)[..., None]).astype(dtype)
    return out
