"""Small corrections to LED position and tilt: the bare-LED sensitivity of the light field.

The traced model's fields ``V_i`` come from the sensor's nominal geometry; a real ring has
LEDs a fraction of a millimetre off and tilted by a degree or two. To first order a change
``theta_i`` of LED ``i``'s position ``(dx, dy, dz)`` (optical frame, mm) and tilt ``(ax, ay)``
(radians, rotations of the emission axis about optical ``x`` and ``y``) changes its field by
``sum_k theta_ik D_ik`` with ``D_ik = dV_i / dtheta_ik``. :func:`geometry_basis` computes
``D`` by central finite differences of the closed-form bare-LED field
(:func:`sim.point_source.point_source_field`) around the given positions; for a ray-traced
``V`` (lens included) this is the stand-in sensitivity, used to first order only.
"""

from __future__ import annotations

import numpy as np

from sim.point_source import point_source_field

__all__ = ["GEOMETRY_PARAMS", "geometry_basis", "tilt_axes"]

#: The per-LED parameters of :func:`geometry_basis`, in order.
GEOMETRY_PARAMS = ("dx_mm", "dy_mm", "dz_mm", "tilt_x_rad", "tilt_y_rad")


def tilt_axes(axes: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """Rotate unit axes ``(L, 3)`` by ``tilt (L, 2)`` radians about optical ``x`` then ``y``.

    Examples
    --------
    >>> a = tilt_axes(np.array([[0.0, 0, 1]]), np.array([[0.0, np.pi / 2]]))
    >>> np.round(a, 6).tolist()
    [[1.0, 0.0, 0.0]]
    """
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    tilt = np.asarray(tilt, dtype=np.float64).reshape(-1, 2)
    out = np.empty_like(axes)
    for i, (a, (tx, ty)) in enumerate(zip(axes, tilt)):
        cx, sx, cy, sy = np.cos(tx), np.sin(tx), np.cos(ty), np.sin(ty)
        rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        v = ry @ rx @ a
        out[i] = v / np.linalg.norm(v)
    return out


def geometry_basis(positions: np.ndarray, axes: np.ndarray | None, shape: tuple[int, int], mm_per_px: float,
                   gel_z: float, *, m: float = 1.0, cone_half_angle_deg: float = 60.0, step_mm: float = 0.05,
                   step_rad: float = 0.005) -> np.ndarray:
    """``D (L, 5, H, W, 3)``: derivative of each LED's field by its position and tilt.

    Parameters
    ----------
    positions : ndarray, shape (L, 3)
        LED positions, optical frame (mm).
    axes : ndarray, shape (L, 3), optional
        Emission axes (default: all along optical ``+z``, toward the gel).
    shape : (H, W)
    mm_per_px, gel_z : float
    m, cone_half_angle_deg : float
        Emission profile of :func:`sim.point_source.point_source_field`.
    step_mm, step_rad : float
        Central-difference steps.

    Returns
    -------
    ndarray, shape (L, 5, H, W, 3), float64
        Parameters in :data:`GEOMETRY_PARAMS` order; reconstruction-frame vectors per unit
        parameter (W/mm^2 per mm or per radian).

    Examples
    --------
    Moving an LED toward the gel (``+dz``) brightens the pixel right above it:

    >>> D = geometry_basis(np.array([[0.0, 0, 0]]), None, (1, 1), 1.0, 10.0)
    >>> D.shape, bool(D[0, 2, 0, 0, 2] > 0)
    ((1, 5, 1, 1, 3), True)
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(positions)
    axes = np.tile([0.0, 0.0, 1.0], (n, 1)) if axes is None else np.asarray(axes, dtype=np.float64).reshape(n, 3)
    h, w = int(shape[0]), int(shape[1])
    kw = dict(m=m, cone_half_angle_deg=cone_half_angle_deg, dtype=np.float64)
    D = np.zeros((n, len(GEOMETRY_PARAMS), h, w, 3))
    for i in range(n):
        p, a = positions[i:i + 1], axes[i:i + 1]
        for k in range(3):
            e = np.zeros((1, 3))
            e[0, k] = step_mm
            D[i, k] = (point_source_field(p + e, a, (h, w), mm_per_px, gel_z, **kw)[0]
                       - point_source_field(p - e, a, (h, w), mm_per_px, gel_z, **kw)[0]) / (2 * step_mm)
        for k in range(2):
            t = np.zeros((1, 2))
            t[0, k] = step_rad
            D[i, 3 + k] = (point_source_field(p, tilt_axes(a, t), (h, w), mm_per_px, gel_z, **kw)[0]
                           - point_source_field(p, tilt_axes(a, -t), (h, w), mm_per_px, gel_z, **kw)[0]) / (2 * step_rad)
    return D
