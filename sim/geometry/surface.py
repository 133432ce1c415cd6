"""The height-field type shared by every contact shape, and the operations on it.

A :class:`HeightField` stores heights *and* their exact gradients. Keeping the gradients (not
the normals) is what makes composition exact: texture adds gradients, smoothing filters them
with the derivative of the same Gaussian, and normals come from
:func:`pipeline.base.frames.gradients_to_normals` only at the end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.base.frames import gradients_to_normals, pixel_to_recon

__all__ = ["HeightField", "flat", "combine", "smooth", "recon_grid"]


@dataclass
class HeightField:
    """A deformed gel surface sampled on the camera's pixel grid.

    Attributes
    ----------
    height : ndarray, shape (H, W), float64
        Heights in mm, reconstruction frame (positive toward the camera).
    p, q : ndarray, shape (H, W), float64
        Exact gradients ``dh/dx`` and ``dh/dy`` in the reconstruction frame (mm per mm).
    contact : ndarray, shape (H, W), bool
        Pixels where an indenter touches the gel.
    mm_per_px : float
        Pixel pitch on the gel.
    """

    height: np.ndarray
    p: np.ndarray
    q: np.ndarray
    contact: np.ndarray
    mm_per_px: float

    def __post_init__(self):
        h = np.asarray(self.height, dtype=np.float64)
        if h.ndim != 2:
            raise ValueError(f"HeightField: height must have shape (H, W), got {h.shape}")
        for name in ("p", "q", "contact"):
            a = np.asarray(getattr(self, name))
            if a.shape != h.shape:
                raise ValueError(f"HeightField: {name} must have shape {h.shape}, got {a.shape}")
        if not (np.all(np.isfinite(h)) and np.all(np.isfinite(self.p)) and np.all(np.isfinite(self.q))):
            raise ValueError("HeightField: height or gradients contain NaN or Inf")
        if not self.mm_per_px > 0:
            raise ValueError(f"HeightField: mm_per_px must be > 0, got {self.mm_per_px}")
        self.height = h
        self.p = np.asarray(self.p, dtype=np.float64)
        self.q = np.asarray(self.q, dtype=np.float64)
        self.contact = np.asarray(self.contact, dtype=bool)
        self.mm_per_px = float(self.mm_per_px)

    @property
    def shape(self) -> tuple[int, int]:
        """Image size ``(H, W)``."""
        return int(self.height.shape[0]), int(self.height.shape[1])

    @property
    def normals(self) -> np.ndarray:
        """Unit normals ``(H, W, 3)`` in the reconstruction frame, from the exact gradients."""
        return gradients_to_normals(self.p, self.q)


def recon_grid(shape: tuple[int, int], mm_per_px: float, center=(0.0, 0.0)):
    """Reconstruction-frame ``(x, y)`` (mm) of every pixel, relative to ``center``.

    Parameters
    ----------
    shape : (H, W)
    mm_per_px : float
    center : (x, y)
        Point of the gel (reconstruction frame, mm; ``(0, 0)`` is the optical axis).

    Returns
    -------
    x, y : ndarray, shape (H, W)

    Examples
    --------
    >>> x, y = recon_grid((3, 3), 1.0)
    >>> x[0].tolist(), y[:, 0].tolist()
    ([-1.0, 0.0, 1.0], [1.0, 0.0, -1.0])
    """
    h, w = _check_shape(shape)
    if not mm_per_px > 0:
        raise ValueError(f"recon_grid: mm_per_px must be > 0, got {mm_per_px}")
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    x, y = pixel_to_recon(rows, cols, (h, w), mm_per_px)
    cx, cy = (float(c) for c in center)
    return x - cx + 0.0, y - cy + 0.0  # + 0.0 turns -0.0 into 0.0


def _check_shape(shape) -> tuple[int, int]:
    if len(tuple(shape)) != 2 or min(int(s) for s in shape) < 1:
        raise ValueError(f"expected an image shape (H, W) with H, W >= 1, got {tuple(shape)}")
    return int(shape[0]), int(shape[1])


def flat(shape: tuple[int, int], mm_per_px: float) -> HeightField:
    """The undeformed gel: zero height, normals ``(0, 0, 1)``, no contact.

    Examples
    --------
    >>> flat((2, 3), 0.1).normals[0, 0].tolist()
    [0.0, 0.0, 1.0]
    """
    h, w = _check_shape(shape)
    z = np.zeros((h, w))
    return HeightField(z, z.copy(), z.copy(), np.zeros((h, w), bool), mm_per_px)


def combine(fields: list[HeightField]) -> HeightField:
    """Several indenters pressing at once: the gel follows the highest one at each pixel.

    Heights are the pointwise maximum; gradients and contact come from the field that wins
    at that pixel (ties keep the first), so normals stay exact away from the seams where two
    indenters meet.

    Examples
    --------
    >>> from sim.geometry import sphere
    >>> a = sphere((20, 40), 0.1, 1.0, 0.3, center=(-1.0, 0.0))
    >>> b = sphere((20, 40), 0.1, 1.0, 0.2, center=(1.0, 0.0))
    >>> c = combine([a, b])
    >>> round(float(c.height.max()), 6) == round(float(a.height.max()), 6), int(c.contact.sum()) > int(a.contact.sum())
    (True, True)
    """
    if not fields:
        raise ValueError("combine: need at least one HeightField")
    shapes = {f.shape for f in fields}
    pitches = {f.mm_per_px for f in fields}
    if len(shapes) != 1 or len(pitches) != 1:
        raise ValueError(f"combine: fields differ in shape {sorted(shapes)} or mm_per_px {sorted(pitches)}")
    heights = np.stack([f.height for f in fields])
    win = np.argmax(heights, axis=0)  # first maximum wins ties

    def pick(name):
        return np.take_along_axis(np.stack([getattr(f, name) for f in fields]), win[None], 0)[0]

    contact = np.any(np.stack([f.contact for f in fields]), axis=0)
    return HeightField(pick("height"), pick("p"), pick("q"), contact, fields[0].mm_per_px)


def smooth(field: HeightField, sigma_mm: float) -> HeightField:
    """Gel smoothing of sharp edges: a Gaussian blur of the surface (an optional effect).

    The elastomer cannot follow an indenter's sharp edge exactly; a Gaussian of standard
    deviation ``sigma_mm`` models that. Heights are blurred, and the gradients are the exact
    derivatives of the blurred heights (derivative-of-Gaussian filters of the original
    heights), so the steps of a flat punch become finite slopes. The contact mask is kept.

    Examples
    --------
    >>> from sim.geometry import flat_punch
    >>> f = flat_punch((40, 40), 0.1, radius=1.0, depth=0.3, edge_radius=0.0)
    >>> s = smooth(f, 0.15)
    >>> bool(s.height.max() < f.height.max() + 1e-12), bool(np.abs(s.p).max() > 0.5)
    (True, True)
    """
    from scipy import ndimage  # here: a live start imports this module, never smooths (docs/live.md)

    if not sigma_mm >= 0:
        raise ValueError(f"smooth: sigma_mm must be >= 0, got {sigma_mm}")
    if sigma_mm == 0:
        return field
    s = sigma_mm / field.mm_per_px
    h = ndimage.gaussian_filter(field.height, s, mode="nearest")
    # Derivatives along columns (+x) and rows (+row = -y), converted to mm per mm.
    dcol = ndimage.gaussian_filter(field.height, s, order=(0, 1), mode="nearest") / field.mm_per_px
    drow = ndimage.gaussian_filter(field.height, s, order=(1, 0), mode="nearest") / field.mm_per_px
    return HeightField(h, dcol, -drow, field.contact.copy(), field.mm_per_px)
