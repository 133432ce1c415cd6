"""Gels with printed markers: find the dark dots, keep them out of calibration, fill them in.

Many tactile gels carry a grid of small dark dots for shear tracking. Under them the coating
does not reflect the LEDs, so their pixels say nothing about the surface normal. This module

- **finds** them in the no-contact reference (:func:`detect_markers`): the darkness relative to
  the local background, ``1 - I / median_filter(I)``, removes the sensor's uneven lighting;
  :func:`skimage.feature.blob_log` finds the dots on it and each becomes a disc of radius
  ``sqrt(2) sigma + grow_px``;
- or reads them from a **mask image** (non-zero = marker) (:func:`read_marker_mask`);
- and they are **filled** in before normals are solved
  (:func:`pipeline.normals.prepare.fill_markers`, an image operation: OpenCV inpainting, per
  channel in float32), and the pixels are marked invalid in the normal maps
  (:func:`calibration.normal_maps.predict_normal_maps`);
- :func:`calibration.samples.collect_samples` leaves them out of the calibration samples.

A marker moves with the gel under a press and leaves the reference's mask: the dots are
also found in every press (:func:`press_markers`), each press filled where its own dots are.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.base.errors import UserError
from pipeline.normals.prepare import check_marker_mask

__all__ = ["detect_markers", "read_marker_mask", "resolve_markers", "draw_markers", "press_markers"]


def _grey(image: np.ndarray) -> np.ndarray:
    """Mean over patterns and channels: ``(P, H, W, C)``, ``(H, W, C)`` or ``(H, W)`` -> ``(H, W)``."""
    a = np.asarray(image, np.float64)
    if a.ndim == 4:
        return a.mean(axis=(0, 3))
    if a.ndim == 3:
        return a.mean(axis=2)
    if a.ndim == 2:
        return a
    raise ValueError(f"detect_markers: reference must be (P, H, W, C), (H, W, C) or (H, W), got {a.shape}")


def detect_markers(reference: np.ndarray, *, min_sigma: float = 0.7, max_sigma: float | None = None,
                   threshold: float = 0.08, grow_px: float = 0.5, background_px: int | None = None) -> np.ndarray:
    """Dark dots of a no-contact reference frame as a bool mask ``(H, W)``.

    Parameters
    ----------
    reference : ndarray, shape (P, H, W, C), (H, W, C) or (H, W)
    min_sigma, max_sigma : float
        Scale range of the dots (px; a dot of radius r has sigma about r / sqrt(2)); default
        ``max_sigma`` 1 % of the image diagonal, at least 3.
    threshold : float
        Minimum darkness response (``blob_log`` threshold on ``1 - I / background``): 0.08
        finds dots at least about 15 % darker than the gel around them.
    grow_px : float
        Margin added around each dot (blur of the print and small motion). 0.5 px: on dots
        drawn onto the shared real frames it covers every darkened pixel; 1 px masks 2.3x as
        many pixels and, filled in, raised the test-press error of the MLP by 1.3 deg
        (0.05 deg with 0.5 px).
    background_px : int, optional
        Size of the median filter that estimates the gel without dots (default: 4 x the largest
        dot diameter, odd).

    Returns
    -------
    ndarray, shape (H, W), bool

    Examples
    --------
    >>> ref = np.full((40, 60, 3), 120.0)
    >>> yy, xx = np.mgrid[:40, :60]
    >>> ref[(yy - 20) ** 2 + (xx - 30) ** 2 <= 4] = 30.0
    >>> m = detect_markers(ref)
    >>> bool(m[20, 30]), bool(m[5, 5]), 10 < int(m.sum()) < 60
    (True, False, True)
    """
    from scipy import ndimage
    from skimage.feature import blob_log

    g = _grey(reference)
    h, w = g.shape
    if max_sigma is None:
        max_sigma = max(3.0, 0.01 * float(np.hypot(h, w)))
    size = background_px or int(2 * round(4 * 2 * np.sqrt(2) * max_sigma) + 1)
    bg = ndimage.median_filter(g, size=size, mode="reflect")
    dark = np.clip(1.0 - g / np.maximum(bg, 1e-6), 0.0, 1.0)
    blobs = blob_log(dark, min_sigma=min_sigma, max_sigma=max_sigma, num_sigma=8, threshold=threshold)
    mask = np.zeros((h, w), bool)
    yy, xx = np.mgrid[:h, :w]
    for y, x, s in blobs:
        r = np.sqrt(2.0) * s + grow_px
        y0, y1 = int(max(0, np.floor(y - r))), int(min(h, np.ceil(y + r) + 1))
        x0, x1 = int(max(0, np.floor(x - r))), int(min(w, np.ceil(x + r) + 1))
        mask[y0:y1, x0:x1] |= (yy[y0:y1, x0:x1] - y) ** 2 + (xx[y0:y1, x0:x1] - x) ** 2 <= r * r
    return mask


def press_markers(frames: np.ndarray, reference_mask: np.ndarray, *, threshold: float = 0.3,
                  grow_px: float = 1.0) -> np.ndarray:
    """Each press's dots, with the reference's mask ``(H, W)`` added: ``(K, H, W)`` bool.

    In each press, a pixel is a dot where it is more than ``threshold`` darker than the gel
    around it (the grey image over a morphological closing as large as three of the
    reference's dots: the closing fills the dots and keeps the shading), grown by ``grow_px``.
    A closing per frame costs milliseconds where :func:`detect_markers`' median filter costs
    seconds on a 640 x 480 frame.

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
    reference_mask : ndarray, shape (H, W), bool
        The reference's dots (:func:`detect_markers`); their size sets the closing's.

    Examples
    --------
    >>> f = np.full((1, 1, 30, 30, 3), 100.0); f[0, 0, 10:13, 20:23] = 30.0
    >>> ref = np.zeros((30, 30), bool); ref[4:7, 4:7] = True
    >>> m = press_markers(f, ref)
    >>> bool(m[0, 11, 21]), bool(m[0, 5, 5]), bool(m[0, 25, 5])
    (True, True, False)
    """
    import cv2
    from scipy import ndimage

    f = np.asarray(frames, np.float32)
    if f.ndim != 5:
        raise ValueError(f"press_markers: frames must be (K, P, H, W, C), got {f.shape}")
    ref = np.asarray(reference_mask, bool)
    labels, n = ndimage.label(ref)
    dot = 2.0 * np.sqrt(ref.sum() / max(n, 1) / np.pi) if n else 3.0  # a typical dot's diameter
    size = int(2 * round(1.5 * dot) + 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (int(2 * round(grow_px) + 1),) * 2)
    out = np.empty((len(f),) + ref.shape, bool)
    for k in range(len(f)):
        g = f[k].mean(axis=(0, 3))
        bg = cv2.morphologyEx(g, cv2.MORPH_CLOSE, kernel)
        dark = (1.0 - g / np.maximum(bg, 1e-6)) > threshold
        out[k] = cv2.dilate(dark.astype(np.uint8), grow).astype(bool) | ref
    return out


def read_marker_mask(path: str | Path, shape: tuple[int, int]) -> np.ndarray:
    """A marker mask image (non-zero = marker, any channel) as bool ``(H, W)``; checked against ``shape``."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such marker mask (expected an image, non-zero on the markers, or 'auto'/'none')")
    img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if img is None:
        raise UserError(f"{path}: not a readable image (marker mask)")
    m = (img != 0) if img.ndim == 2 else (img != 0).any(axis=2)
    if m.shape != tuple(shape):
        raise UserError(f"{path}: marker mask is {m.shape[1]}x{m.shape[0]} px but the frames are "
                        f"{shape[1]}x{shape[0]} px")
    return m


def resolve_markers(spec, reference: np.ndarray) -> np.ndarray | None:
    """``"auto"`` (:func:`detect_markers` on ``reference``), ``"none"``/None, or a mask image path."""
    if spec is None or (isinstance(spec, str) and spec == "none"):
        return None
    shape = tuple(np.asarray(reference).shape[-3:-1]) if np.asarray(reference).ndim >= 3 else np.asarray(reference).shape
    if isinstance(spec, str) and spec == "auto":
        return detect_markers(reference)
    if isinstance(spec, np.ndarray):
        return check_marker_mask(spec, shape)
    return read_marker_mask(spec, shape)


def draw_markers(images: np.ndarray, spacing_px: float = 10.0, radius_px: float = 1.5, darkness: float = 0.75,
                 offset_px: tuple[float, float] = (4.0, 5.0)) -> tuple[np.ndarray, np.ndarray]:
    """Print a grid of dark dots onto frames (the same place in every frame), for tests and benchmarks.

    Parameters
    ----------
    images : ndarray, shape (..., H, W, C)
    spacing_px, radius_px : float
        Grid pitch and dot radius.
    darkness : float
        Fraction of the light a dot absorbs (0.75: the dot shows a quarter of the gel's value).
    offset_px : (row, col)
        Position of the first dot.

    Returns
    -------
    marked : ndarray, same shape and dtype as ``images``
    mask : ndarray, shape (H, W), bool
        The dots' pixels.
    """
    a = np.asarray(images)
    h, w = a.shape[-3:-1]
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    d = np.full((h, w), np.inf)
    for y in np.arange(offset_px[0], h, spacing_px):
        for x in np.arange(offset_px[1], w, spacing_px):
            d = np.minimum(d, np.hypot(yy - y, xx - x))
    # Anti-aliased edge (half a pixel), as a printed dot imaged by a camera.
    cover = np.clip(radius_px + 0.5 - d, 0.0, 1.0)
    marked = a.astype(np.float64) * (1.0 - darkness * cover)[:, :, None]
    if a.dtype.kind in "ui":
        marked = np.round(marked)
    return marked.astype(a.dtype), cover > 0
