"""Coordinate conventions: the one place that says which way every axis points.

Every other module converts between frames with these functions instead of flipping signs
locally; ``tests/sim/test_frames.py`` pins each sign.

Optical frame (the paper's, used by the ray tracer)
    Millimetres. Origin at the centre of the LED ring, on the LED plane. ``+z`` points from
    the LEDs toward the gel, so the gel (imaging plane) lies at some ``z = z_gel > 0``. The
    camera sits below the ring and looks up along ``+z``.

Reconstruction frame (normals, light vectors, heights)
    ``+z`` points from the gel toward the camera, so a flat gel has ``n = (0, 0, 1)`` and a
    ball pressed into the gel gives a positive height (a bump toward the camera). The frame
    is the optical frame rotated by 180 degrees about ``x``:
    ``x_r = x_o``, ``y_r = -y_o``, ``z_r = -z_o`` (a proper rotation, so it stays
    right-handed and cross products keep their meaning).

Pixels
    Images are ``(H, W)`` or ``(H, W, C)`` arrays indexed ``[row, col]``, channels in RGB
    order (never BGR: OpenCV frames are converted on the way in). With the default
    orthographic camera of scale ``s`` mm per pixel, centred on the optical axis::

        x_o = (col - cx) * s        y_o = (row - cy) * s
        x_r = (col - cx) * s        y_r = -(row - cy) * s

    where ``cx = (W - 1) / 2`` and ``cy = (H - 1) / 2``. So in the reconstruction frame
    columns grow along ``+x`` and rows grow along ``-y``: the image is displayed as the
    camera sees the gel, ``y`` up.

Heights and normals
    A height map ``h[row, col]`` (mm, reconstruction ``z``) describes the surface
    ``z_r = h(x_r, y_r)``; its unit normal is ``(-dh/dx, -dh/dy, 1) / norm`` with
    ``dh/dx = dh/dcol / s`` and ``dh/dy = -dh/drow / s``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "CHANNELS",
    "pixel_centers",
    "pixel_to_optical",
    "pixel_to_recon",
    "optical_to_recon",
    "recon_to_optical",
    "gradients_to_normals",
    "normals_to_gradients",
    "gradients_to_pixel_steps",
    "pixel_steps_to_gradients",
    "normals_from_height",
]

#: Channel order of every image in the project.
CHANNELS = ("R", "G", "B")

# The 180-degree rotation about x that takes optical vectors to reconstruction vectors.
# It is its own inverse.
_FLIP = np.array([1.0, -1.0, -1.0])


def pixel_centers(shape: tuple[int, int]) -> tuple[float, float]:
    """Return the optical-axis pixel ``(cy, cx)`` of an image of ``shape = (H, W)``.

    Examples
    --------
    >>> pixel_centers((240, 320))
    (119.5, 159.5)
    """
    h, w = int(shape[0]), int(shape[1])
    return (h - 1) / 2.0, (w - 1) / 2.0


def pixel_to_optical(rows, cols, shape, mm_per_px: float):
    """Map pixel coordinates to optical-frame ``(x, y)`` in mm (orthographic camera).

    Parameters
    ----------
    rows, cols : array_like
        Pixel coordinates (may be fractional), broadcastable against each other.
    shape : (H, W)
        Image size; the optical axis passes through the image centre.
    mm_per_px : float
        Pixel pitch on the gel.

    Returns
    -------
    x, y : ndarray
        Optical-frame coordinates in mm.

    Examples
    --------
    >>> x, y = pixel_to_optical(0, 2, (3, 3), 0.5)
    >>> float(x), float(y)
    (0.5, -0.5)
    """
    cy, cx = pixel_centers(shape)
    rows = np.asarray(rows, dtype=float)
    cols = np.asarray(cols, dtype=float)
    return (cols - cx) * mm_per_px, (rows - cy) * mm_per_px


def pixel_to_recon(rows, cols, shape, mm_per_px: float):
    """Map pixel coordinates to reconstruction-frame ``(x, y)`` in mm.

    Examples
    --------
    >>> x, y = pixel_to_recon(0, 2, (3, 3), 0.5)
    >>> float(x), float(y)
    (0.5, 0.5)
    """
    x, y = pixel_to_optical(rows, cols, shape, mm_per_px)
    return x, -y


def optical_to_recon(v):
    """Rotate vectors ``(..., 3)`` from the optical frame to the reconstruction frame.

    Works on numpy arrays and torch tensors alike (elementwise sign flip of y and z).

    Examples
    --------
    >>> optical_to_recon(np.array([1.0, 2.0, 3.0]))
    array([ 1., -2., -3.])
    """
    if isinstance(v, np.ndarray) or np.isscalar(v) or isinstance(v, (list, tuple)):
        v = np.asarray(v, dtype=float)
        return v * _FLIP
    # torch tensor: build the flip on the tensor's device and dtype.
    flip = v.new_tensor(_FLIP)
    return v * flip


def recon_to_optical(v):
    """Inverse of :func:`optical_to_recon` (the rotation is its own inverse)."""
    return optical_to_recon(v)


def gradients_to_normals(p, q):
    """Unit normals ``(..., 3)`` from surface gradients ``p = dh/dx``, ``q = dh/dy``.

    Both gradients are in the reconstruction frame (mm per mm).

    Examples
    --------
    >>> gradients_to_normals(np.array(0.0), np.array(0.0)).tolist()
    [0.0, 0.0, 1.0]
    """
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    n = np.stack([0.0 - p, 0.0 - q, np.ones_like(p)], axis=-1)  # 0.0 - p avoids -0.0
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def normals_to_gradients(n, min_nz: float = 1e-6, dtype=float):
    """Surface gradients ``(p, q)`` from unit normals ``(..., 3)``.

    ``n_z`` is clamped to at least ``min_nz`` so that grazing normals give large but finite
    gradients rather than Inf. ``dtype`` is the float type of the result (float64 by
    default; the depth integrators keep float32 normals in float32).
    """
    n = np.asarray(n, dtype=dtype)
    nz = np.maximum(n[..., 2], n.dtype.type(min_nz))
    return -n[..., 0] / nz, -n[..., 1] / nz


def gradients_to_pixel_steps(p, q, mm_per_px: float):
    """Height steps per pixel ``(dh/dcol, dh/drow)`` in mm from gradients ``p = dh/dx``, ``q = dh/dy``.

    Columns grow along ``+x`` and rows along ``-y`` (reconstruction frame), so
    ``dh/dcol = p s`` and ``dh/drow = -q s``. The result keeps the float type of ``p``.

    Examples
    --------
    >>> gradients_to_pixel_steps(np.float32(0.5), np.float32(0.25), 0.1)
    (np.float32(0.05), np.float32(-0.025))
    """
    s = np.asarray(p).dtype.type(mm_per_px) if np.asarray(p).dtype.kind == "f" else float(mm_per_px)
    return p * s, -q * s


def pixel_steps_to_gradients(dh_dcol, dh_drow, mm_per_px: float):
    """Inverse of :func:`gradients_to_pixel_steps`: ``(p, q) = (dh/dcol / s, -dh/drow / s)``."""
    return dh_dcol / mm_per_px, -dh_drow / mm_per_px


def normals_from_height(h, mm_per_px: float):
    """Unit normals ``(H, W, 3)`` of a height map ``(H, W)`` by central differences.

    Parameters
    ----------
    h : ndarray, shape (H, W)
        Heights in mm, positive toward the camera.
    mm_per_px : float
        Pixel pitch.

    Examples
    --------
    A plane rising toward +x (toward larger columns) tilts its normal toward -x:

    >>> h = np.tile(np.arange(4.0), (3, 1)) * 0.1
    >>> n = normals_from_height(h, 0.1)
    >>> bool(n[1, 1, 0] < 0), bool(abs(n[1, 1, 1]) < 1e-12)
    (True, True)
    """
    h = np.asarray(h, dtype=float)
    if h.ndim != 2:
        raise ValueError(f"normals_from_height: expected a height map of shape (H, W), got {h.shape}")
    dh_drow, dh_dcol = np.gradient(h)
    return gradients_to_normals(*pixel_steps_to_gradients(dh_dcol, dh_drow, mm_per_px))
