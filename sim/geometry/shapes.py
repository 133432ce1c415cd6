"""Indenter shapes pressed into the gel, with exact analytic gradients.

The gel is modelled as following the indenter inside the contact and staying flat outside
(no bulge): the height is the part of the indenter surface that lies above the undeformed
gel. ``depth`` is how far the indenter's lowest point pushes past the gel plane, i.e. the
peak height of the impression (mm, toward the camera). Positions are reconstruction-frame
``(x, y)`` in mm with ``(0, 0)`` on the optical axis; angles are degrees from ``+x`` toward
``+y`` (counter-clockwise as the camera sees the gel).
"""

from __future__ import annotations

import math

import numpy as np

from sim.geometry.surface import HeightField, recon_grid

__all__ = ["sphere", "cap_depth", "cylinder", "flat_punch", "cone", "wedge"]


def _positive(func: str, **values) -> None:
    for k, v in values.items():
        if not (isinstance(v, (int, float, np.floating, np.integer)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{func}: {k} must be a finite number > 0, got {v!r}")


def _axis_coords(x, y, angle_deg):
    """Coordinates along (t) and across (u) a line through the origin at ``angle_deg``."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return x * c + y * s, -x * s + y * c, c, s


def _pointed(func, shape, mm_per_px, half_angle_deg, depth, center):
    """Checks and the grid shared by the pointed shapes; returns (cot(alpha), x, y)."""
    _positive(func, half_angle_deg=half_angle_deg, depth=depth, mm_per_px=mm_per_px)
    if half_angle_deg >= 90:
        raise ValueError(f"{func}: half_angle_deg must be < 90, got {half_angle_deg}")
    x, y = recon_grid(shape, mm_per_px, center)
    return 1.0 / math.tan(math.radians(half_angle_deg)), x, y


def cap_depth(radius, contact_radius):
    """Depth ``d = R - sqrt(R^2 - a^2)`` of a ball of radius ``R`` whose contact disc has radius
    ``a`` (the inverse of the contact radius ``a = sqrt(2 R d - d^2)`` of :func:`sphere`); ``a``
    is capped at ``R`` (a disc wider than the ball means the edge seen is not the contact's
    own). Scalars or arrays.

    Examples
    --------
    >>> round(float(cap_depth(2.0, 1.2)), 6), float(cap_depth(2.0, 3.0))
    (0.4, 2.0)
    """
    a = np.minimum(np.asarray(contact_radius, dtype=np.float64), radius)
    return radius - np.sqrt(radius * radius - a * a)


def sphere(shape, mm_per_px: float, radius: float, depth: float, center=(0.0, 0.0)) -> HeightField:
    """A ball of ``radius`` pressed ``depth`` into the gel (``0 < depth < radius``).

    ``h = sqrt(R^2 - r^2) - (R - d)`` inside the contact circle of radius
    ``a = sqrt(2 R d - d^2)``; the normal there is ``(x, y, sqrt(R^2 - r^2)) / R``, the
    sphere's own outward normal.

    Examples
    --------
    >>> f = sphere((41, 41), 0.1, radius=2.0, depth=0.5)
    >>> round(float(f.height[20, 20]), 12), bool(f.contact[20, 20]), bool(f.contact[0, 0])
    (0.5, True, False)
    """
    _positive("sphere", radius=radius, depth=depth, mm_per_px=mm_per_px)
    if depth >= radius:
        raise ValueError(f"sphere: depth must be < radius ({radius}), got {depth}")
    x, y = recon_grid(shape, mm_per_px, center)
    r2 = x * x + y * y
    a2 = 2 * radius * depth - depth * depth
    inside = r2 < a2
    root = np.sqrt(np.where(inside, radius * radius - r2, 1.0))
    h = np.where(inside, root - (radius - depth), 0.0)
    p = np.where(inside, -x / root, 0.0)
    q = np.where(inside, -y / root, 0.0)
    return HeightField(h, p, q, inside, mm_per_px)


def cylinder(shape, mm_per_px: float, radius: float, depth: float, center=(0.0, 0.0), angle_deg: float = 0.0,
             length: float | None = None) -> HeightField:
    """A cylinder lying on the gel, axis along ``angle_deg``, pressed ``depth`` (< radius).

    ``length`` (mm) cuts the cylinder with flat ends (a step in the height map at the ends);
    ``None`` makes it run across the whole image.

    Examples
    --------
    >>> f = cylinder((21, 41), 0.1, radius=1.0, depth=0.2)
    >>> bool(np.allclose(f.height[5], f.height[15])), bool(np.allclose(f.p, 0.0))
    (True, True)
    """
    _positive("cylinder", radius=radius, depth=depth, mm_per_px=mm_per_px)
    if depth >= radius:
        raise ValueError(f"cylinder: depth must be < radius ({radius}), got {depth}")
    if length is not None:
        _positive("cylinder", length=length)
    x, y = recon_grid(shape, mm_per_px, center)
    t, u, c, s = _axis_coords(x, y, angle_deg)
    a2 = 2 * radius * depth - depth * depth
    inside = u * u < a2
    if length is not None:
        inside &= np.abs(t) <= length / 2
    root = np.sqrt(np.where(inside, radius * radius - u * u, 1.0))
    h = np.where(inside, root - (radius - depth), 0.0)
    dh_du = np.where(inside, -u / root, 0.0)
    # u = -x sin + y cos, so du/dx = -sin, du/dy = cos.
    return HeightField(h, dh_du * -s, dh_du * c, inside, mm_per_px)


def flat_punch(shape, mm_per_px: float, radius: float, depth: float, center=(0.0, 0.0),
               edge_radius: float = 0.1) -> HeightField:
    """A flat-ended cylindrical punch of face ``radius`` with a rounded edge of ``edge_radius``.

    The face (``r <= radius``) sits at ``h = depth``; around it a quarter-circle fillet of
    radius ``e`` centred at ``(radius, depth - e)`` falls toward the gel. If ``e < depth`` the
    fillet ends at height ``depth - e`` and the impression has a vertical wall there (a step
    in the height map, zero area); if ``e >= depth`` the fillet meets the gel smoothly enough
    to have finite slope. ``edge_radius=0`` is the sharp-edged punch (a pure step).

    Examples
    --------
    >>> f = flat_punch((41, 41), 0.1, radius=1.0, depth=0.3, edge_radius=0.5)
    >>> round(float(f.height[20, 20]), 12), float(f.p[20, 20])
    (0.3, 0.0)
    """
    _positive("flat_punch", radius=radius, depth=depth, mm_per_px=mm_per_px)
    if not (math.isfinite(edge_radius) and edge_radius >= 0):
        raise ValueError(f"flat_punch: edge_radius must be >= 0, got {edge_radius!r}")
    x, y = recon_grid(shape, mm_per_px, center)
    r = np.hypot(x, y)
    e = float(edge_radius)
    face = r <= radius
    s = r - radius  # distance past the face edge
    if e > 0:
        z0 = depth - e  # height of the fillet's centre
        # Fillet height e^2 - s^2 under the root; it must stay above the gel (h > 0).
        reach = e if z0 >= 0 else math.sqrt(e * e - z0 * z0)
        fillet = (~face) & (s < reach)
        root = np.sqrt(np.where(fillet, e * e - s * s, 1.0))
        h_fil = z0 + root
        dh_dr = -s / root
    else:
        fillet = np.zeros_like(face)
        h_fil = dh_dr = np.zeros_like(r)
    h = np.where(face, depth, np.where(fillet, h_fil, 0.0))
    rs = np.where(r > 0, r, 1.0)
    p = np.where(fillet, dh_dr * x / rs, 0.0)
    q = np.where(fillet, dh_dr * y / rs, 0.0)
    return HeightField(h, p, q, face | fillet, mm_per_px)


def cone(shape, mm_per_px: float, half_angle_deg: float, depth: float, center=(0.0, 0.0)) -> HeightField:
    """A cone, tip first, of apex half-angle ``half_angle_deg``, pressed ``depth``.

    ``h = depth - r cot(alpha)`` where positive. The apex is not differentiable; the pixel
    exactly on it gets ``n = (0, 0, 1)`` (the mean of the normals around it).

    Examples
    --------
    >>> f = cone((41, 41), 0.1, half_angle_deg=45.0, depth=1.0)
    >>> round(float(f.height[20, 20]), 12), round(float(f.p[20, 25]), 12)  # falls toward +x
    (1.0, -1.0)
    """
    slope, x, y = _pointed("cone", shape, mm_per_px, half_angle_deg, depth, center)
    r = np.hypot(x, y)
    h = depth - r * slope
    inside = h > 0
    rs = np.where(r > 0, r, 1.0)
    p = np.where(inside & (r > 0), -slope * x / rs, 0.0)
    q = np.where(inside & (r > 0), -slope * y / rs, 0.0)
    return HeightField(np.where(inside, h, 0.0), p, q, inside, mm_per_px)


def wedge(shape, mm_per_px: float, half_angle_deg: float, depth: float, center=(0.0, 0.0),
          angle_deg: float = 0.0) -> HeightField:
    """A knife edge (wedge) along ``angle_deg``, of half-angle ``half_angle_deg``, pressed ``depth``.

    ``h = depth - |u| cot(alpha)`` where positive, ``u`` the distance across the edge line.
    Pixels exactly on the ridge get ``n = (0, 0, 1)``.

    Examples
    --------
    >>> f = wedge((21, 41), 0.1, half_angle_deg=45.0, depth=0.5, angle_deg=90.0)
    >>> round(float(f.height[10, 20]), 12), round(float(f.p[10, 22]), 12)
    (0.5, -1.0)
    """
    slope, x, y = _pointed("wedge", shape, mm_per_px, half_angle_deg, depth, center)
    _, u, c, s = _axis_coords(x, y, angle_deg)
    h = depth - np.abs(u) * slope
    inside = h > 0
    dh_du = np.where(inside, -slope * np.sign(u), 0.0)
    return HeightField(np.where(inside, h, 0.0), dh_du * -s, dh_du * c, inside, mm_per_px)
