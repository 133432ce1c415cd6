"""Height maps read from files: 16-bit PNG or NPY, with a millimetre scale."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.frames import normals_from_height, normals_to_gradients
from sim.geometry.surface import HeightField

__all__ = ["height_from_file"]


def height_from_file(path, mm_per_px: float, mm_per_unit: float = 1.0, shape: tuple[int, int] | None = None,
                     contact_threshold: float = 1e-9) -> HeightField:
    """Read a height map (mm toward the camera) from a ``.npy`` or 16-bit ``.png`` file.

    Parameters
    ----------
    path : str or Path
        ``.npy`` (any real 2-D array) or ``.png`` (single channel, 8 or 16 bit).
    mm_per_px : float
        Pixel pitch of the map on the gel.
    mm_per_unit : float
        Height scale: mm per stored unit (for a PNG, mm per grey level; for NPY, 1 if the
        file is already in mm).
    shape : (H, W), optional
        Resample to this size (bilinear); ``mm_per_px`` is then scaled so the map covers the
        same gel area.
    contact_threshold : float
        Heights above this (mm) count as contact.

    Returns
    -------
    HeightField
        Gradients by central differences: a sampled map has no analytic normals.

    Raises
    ------
    UserError
        Missing file, unknown extension, wrong number of dimensions or non-finite values,
        named with the file.

    Examples
    --------
    >>> import tempfile, os
    >>> d = tempfile.mkdtemp(); f = os.path.join(d, "h.npy")
    >>> np.save(f, np.ones((4, 5)) * 2.0)
    >>> height_from_file(f, 0.1, mm_per_unit=0.5).height.max().item()
    1.0
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: height map file not found")
    ext = path.suffix.lower()
    if ext == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except Exception as exc:  # numpy raises several types for bad files
            raise UserError(f"{path}: not a readable .npy array ({exc})") from None
    elif ext == ".png":
        import cv2

        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise UserError(f"{path}: not a readable PNG")
        if raw.ndim == 3:
            raise UserError(f"{path}: height map PNG must have one channel, got shape {raw.shape}")
    else:
        raise UserError(f"{path}: height map must be .npy or .png, got '{ext}'")
    if raw.ndim != 2 or raw.dtype.kind not in "uif":
        raise UserError(f"{path}: height map must be a real 2-D array (H, W), got {raw.dtype} {raw.shape}")
    h = raw.astype(np.float64) * float(mm_per_unit)
    if not np.all(np.isfinite(h)):
        raise UserError(f"{path}: height map contains NaN or Inf")
    if shape is not None and tuple(shape) != h.shape:
        import cv2

        new_pitch = mm_per_px * h.shape[1] / shape[1]
        h = cv2.resize(h, (int(shape[1]), int(shape[0])), interpolation=cv2.INTER_LINEAR)
        mm_per_px = new_pitch
    p, q = normals_to_gradients(normals_from_height(h, mm_per_px))
    return HeightField(h, p, q, h > contact_threshold, mm_per_px)
