"""Far-field (directional) lights: a photometric-stereo light dome, its illumination model and
cast shadows of a height map along each light direction.

A photometric-stereo benchmark rig (DiLiGenT: 96 LEDs on a grid about 1.5 m from a small
object, directions within about 45 degrees of the view axis) lights every pixel from the
same direction with the same irradiance per light. :func:`far_field_illumination` turns such
lights into an :class:`sim.illumination_model.IlluminationModel` (``V`` the same at every
pixel, ``directions`` set), so the renderer and every effect work on it unchanged; with
``directions`` set the renderer's ``cast_shadows`` effect calls :func:`far_field_visibility`
instead of marching toward LED positions.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.base.frames import recon_to_optical
from sim.illumination_model import IlluminationModel

__all__ = ["dome_lights", "far_field_illumination", "far_field_visibility"]

#: Distance (mm) at which far-field lights are placed in ``led_positions`` (only for tools
#: that need a position; the renderer uses ``directions``).
FAR_MM = 1e6


def dome_lights(rows: int = 8, cols: int = 12, max_angle_deg: float = 45.0, *, intensity_range=(0.6, 1.0),
                tint: float = 0.05, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Light directions and RGB intensities of a planar ``rows x cols`` LED grid facing the object.

    The grid is centred on the view axis with equal spacing, scaled so that its corner LEDs
    are ``max_angle_deg`` from the axis (DiLiGenT: 8 x 12 = 96 LEDs, within about 45 degrees).
    Intensities are per light and channel, like a benchmark's calibrated
    ``light_intensities.txt``: uniform in ``intensity_range`` times a per-channel tint within
    ``1 +- tint``.

    Returns
    -------
    directions : ndarray, shape (rows * cols, 3)
        Unit vectors from the object toward each light, reconstruction frame (+z toward the
        camera), row-major over the grid.
    intensities : ndarray, shape (rows * cols, 3)
        RGB intensity of each light.

    Examples
    --------
    >>> d, e = dome_lights()
    >>> d.shape, e.shape, round(float(np.degrees(np.arccos(d[:, 2].min()))), 6)
    ((96, 3), (96, 3), 45.0)
    """
    if rows < 1 or cols < 1 or rows * cols < 3:
        raise ValueError(f"dome_lights: need at least 3 lights, got rows={rows}, cols={cols}")
    if not 0 < max_angle_deg < 90:
        raise ValueError(f"dome_lights: max_angle_deg must be in (0, 90), got {max_angle_deg}")
    half_c, half_r = (cols - 1) / 2, (rows - 1) / 2
    s = math.tan(math.radians(max_angle_deg)) / max(math.hypot(half_c, half_r), 1e-12)
    yy, xx = np.meshgrid((half_r - np.arange(rows)) * s, (np.arange(cols) - half_c) * s, indexing="ij")
    d = np.stack([xx.ravel(), yy.ravel(), np.ones(rows * cols)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    rng = np.random.default_rng(seed)
    lo, hi = intensity_range
    e = rng.uniform(lo, hi, (rows * cols, 1)) * rng.uniform(1 - tint, 1 + tint, (rows * cols, 3))
    return d, e


def far_field_illumination(directions, shape: tuple[int, int], mm_per_px: float) -> IlluminationModel:
    """An :class:`IlluminationModel` of directional lights: ``V_i(x) = d_i`` at every pixel.

    Light intensities go into the drive (``drive[p, i] = intensity``), as for LEDs.
    ``V`` is a read-only broadcast view (no ``L x H x W`` copy).

    Examples
    --------
    >>> m = far_field_illumination([[0, 0, 1.0], [0.6, 0, 0.8]], (4, 5), 0.1)
    >>> m.V.shape, m.directions.shape, [round(float(v), 6) for v in m.V[1, 3, 4]]
    ((2, 4, 5, 3), (2, 3), [0.6, 0.0, 0.8])
    """
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or not np.isfinite(d).all():
        raise ValueError(f"far_field_illumination: directions must be finite with shape (L, 3), got {d.shape}")
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    if (norm <= 0).any():
        raise ValueError("far_field_illumination: a direction is the zero vector")
    d = d / norm
    H, W = (int(s) for s in shape)
    V = np.broadcast_to(d.astype(np.float32)[:, None, None, :], (len(d), H, W, 3))
    return IlluminationModel(V=V, mm_per_px=float(mm_per_px), led_positions=recon_to_optical(d * FAR_MM), gel_z=0.0,
                             directions=d, meta={"source": "far_field", "count": len(d)})


def far_field_visibility(height, directions, mm_per_px: float, *, eps_px: float = 0.25, device="cpu",
                         dtype=torch.float32) -> torch.Tensor:
    """Cast-shadow visibility ``(L, H*W)`` (1 lit, 0 shadowed) of a height map under directional lights.

    A pixel is shadowed from light ``d`` when the height map rises above the ray
    ``p + t d`` (``t > 0``) somewhere. The ray is sampled once per pixel step along its
    dominant image axis (one column or one row at a time: one of the two coordinates is then
    an integer, so a sample is a linear interpolation of two pixels), for all pixels at once
    as shifted views of the padded map; it stops once the ray has risen above the highest
    point. Outside the image the surface is taken as flat at height 0. A sample must exceed
    the ray by ``eps_px`` pixels of height to block (interpolation on a curved surface).

    Parameters
    ----------
    height : ndarray, shape (H, W)
        Heights in mm, reconstruction frame.
    directions : ndarray, shape (L, 3)
        Unit directions toward the lights (reconstruction frame). A light straight overhead
        casts no shadow; one at or below the horizon (``d_z <= 0``) is left to the attached
        shadows (visibility 1 here).
    mm_per_px : float

    Examples
    --------
    A 2 mm post at column 3, light from -x at 45 degrees, 1 mm pixels: the pixel behind it
    (where the ray passes 1 mm below the top) is shadowed; two pixels behind, the ray
    grazes the top (within the tolerance) and the pixel is lit.

    >>> h = np.zeros((1, 6)); h[0, 3] = 2.0
    >>> v = far_field_visibility(h, [[-0.7071, 0, 0.7071]], 1.0)
    >>> v.int().tolist()
    [[1, 1, 1, 1, 0, 1]]
    """
    h = np.asarray(height, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    H, W = h.shape
    ht = torch.as_tensor(h, dtype=dtype, device=device)
    hmax = max(float(h.max()), 0.0)
    hmin = min(float(h.min()), 0.0)
    vis = torch.ones((len(d), H * W), dtype=dtype, device=device)
    if hmax - hmin <= 0:
        return vis
    eps = eps_px * mm_per_px
    for i, (dx, dy, dz) in enumerate(d):
        dcol, drow = dx, -dy  # rows grow along -y (pipeline.base.frames)
        horiz = math.hypot(dcol, drow)
        if dz <= 0 or horiz <= 1e-12:
            continue  # overhead light: no cast shadow; below the horizon: attached shadow
        if abs(dcol) >= abs(drow):
            blocked = _march(ht, dcol, drow, dz, horiz, hmax, hmin, eps, mm_per_px)
        else:  # march along rows: the same on the transposed map
            blocked = _march(ht.T, drow, dcol, dz, horiz, hmax, hmin, eps, mm_per_px).T
        vis[i] = (~blocked).reshape(-1).to(dtype)
    return vis


def _march(h: torch.Tensor, da: float, db: float, dz: float, horiz: float, hmax: float, hmin: float, eps: float,
           px: float) -> torch.Tensor:
    """Blocked ``(R, C)`` for a ray stepping one column (``sign(da)``) and ``db / |da|`` rows per step."""
    R, C = h.shape
    sc = 1 if da > 0 else -1
    sr = db / abs(da)  # rows per column step, |sr| <= 1
    rise = px * math.hypot(1.0, sr) * dz / horiz  # ray height gained per step (mm)
    K = min(int(math.ceil((hmax - hmin) / rise)), C + R)  # beyond K the ray is above everything
    pad = K + 2
    hp = torch.nn.functional.pad(h[None, None], (pad, pad, pad, pad))[0, 0]  # 0 outside the image
    blocked = torch.zeros((R, C), dtype=torch.bool, device=h.device)
    for k in range(1, K + 1):
        r = k * sr
        r0 = math.floor(r)
        f = r - r0
        c0 = pad + k * sc
        a = hp[pad + r0:pad + r0 + R, c0:c0 + C]
        s = a if f == 0 else a + f * (hp[pad + r0 + 1:pad + r0 + 1 + R, c0:c0 + C] - a)
        blocked |= s > h + (k * rise + eps)
    return blocked
