"""Training and evaluation samples: pixels with their observations and their true normals.

Each accepted press contributes the pixels inside its contact disc shrunk by
``shrink_px`` (sphere-cap normals, ``contact=True``: the pixels every model is validated on)
and a sparse set of pixels far outside it (flat, ``contact=False``); the no-contact reference
adds flat pixels on a grid (``press = -1``, never held out). Saturated observations are
dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from calibration.truth import sphere_cap

if TYPE_CHECKING:  # an annotation only: calibration.detect imports scipy.ndimage (~0.2 s), which
    # loading a calibration (every live start, via the models) does not need (docs/live.md)
    from calibration.detect import Circle

__all__ = ["RIM_FRACTION", "Samples", "collect_samples"]

#: The margin inside each contact circle left out of the samples, as a fraction of its radius
#: (at least ``shrink_px``). An edge found on a blurred image is uncertain by a few per cent of
#: the radius (docs/calibration.md, "Contact detection"), and a truth disc that reaches past the
#: real contact labels the gel's skirt, whose tilt falls away, as sphere: every model then
#: learns tilts that are too steep.
RIM_FRACTION = 0.1


@dataclass
class Samples:
    """Pixels of a capture with observations and truth.

    Attributes
    ----------
    intensities : ndarray, shape (N, P, C), float32
        Linear observations (dark removed).
    reference : ndarray, shape (N, P, C), float32
        The no-contact reference at the same pixel.
    rows, cols : ndarray, shape (N,), int
    normals : ndarray, shape (N, 3), float64
        True unit normals (reconstruction frame).
    press : ndarray, shape (N,), int
        Press index, ``-1`` for reference pixels.
    contact : ndarray, shape (N,), bool
        Inside a (shrunk) contact disc.
    shape : (H, W)
    radial : ndarray, shape (N,), float, or None
        Distance from the press's circle centre over its contact radius (in [0, 1) on contact
        pixels, 0 elsewhere): where on the cap a pixel lies, for rim weighting.
    images : ndarray, shape (K, P, H, W, C), float32, or None
        The whole frames the samples were drawn from (``press`` indexes them; shared, never
        copied by :meth:`subset`): a model that looks at a pixel's neighbourhood reads them.
    reference_image : ndarray, shape (P, H, W, C), float32, or None
        The whole no-contact reference (the frame of the ``press = -1`` samples).
    """

    intensities: np.ndarray
    reference: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    normals: np.ndarray
    press: np.ndarray
    contact: np.ndarray
    shape: tuple[int, int]
    radial: np.ndarray | None = None
    images: np.ndarray | None = None
    reference_image: np.ndarray | None = None

    def __len__(self) -> int:
        return int(len(self.rows))

    def subset(self, mask: np.ndarray) -> "Samples":
        """The samples where ``mask (N,)`` is True."""
        m = np.asarray(mask, dtype=bool)
        return Samples(self.intensities[m], self.reference[m], self.rows[m], self.cols[m], self.normals[m],
                       self.press[m], self.contact[m], self.shape, None if self.radial is None else self.radial[m],
                       self.images, self.reference_image)

    @property
    def flat_observations(self) -> np.ndarray:
        """``intensities`` as ``(N, P * C)``."""
        return self.intensities.reshape(len(self), -1)


def collect_samples(frames: np.ndarray, reference: np.ndarray, circles: list[Circle], ball_radius_mm: float,
                    mm_per_px: float, *, shrink_px: float = 2.0, rim_fraction: float = RIM_FRACTION,
                    flat_outside: float = 2.0, flat_step: int = 4,
                    saturation: float | None = None, exclude: np.ndarray | None = None) -> Samples:
    """Gather samples from the accepted presses.

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        Linear frames.
    reference : ndarray, shape (P, H, W, C)
    circles : list of Circle, length K
    ball_radius_mm, mm_per_px : float
    shrink_px : float
        Contact pixels lie within ``contact_radius - max(shrink_px, rim_fraction *
        contact_radius)`` (the rim is where the truth is least certain).
    rim_fraction : float
        The margin as a fraction of the contact radius, for large contacts on blurred images
        (:data:`RIM_FRACTION`).
    flat_outside : float
        Flat pixels of a press lie beyond ``flat_outside x`` the ball radius from its centre
        (the gel bulges around the contact).
    flat_step : int
        Grid step of the flat pixels.
    saturation : float, optional
        Observations at or above this value are dropped.
    exclude : ndarray, shape (H, W), bool, optional
        Pixels never sampled (printed gel markers, :mod:`calibration.markers`).

    Returns
    -------
    Samples
    """
    frames = np.asarray(frames, dtype=np.float32)
    reference = np.asarray(reference, dtype=np.float32)
    if frames.ndim != 5 or frames.shape[1:] != reference.shape:
        raise ValueError(f"collect_samples: frames (K, P, H, W, C) and reference (P, H, W, C) expected, got "
                         f"{frames.shape} and {reference.shape}")
    if len(circles) != frames.shape[0]:
        raise ValueError(f"collect_samples: {frames.shape[0]} presses but {len(circles)} circles")
    k_all, p, h, w, c = frames.shape
    rows, cols = np.mgrid[:h, :w]
    grid = (rows % flat_step == 0) & (cols % flat_step == 0)
    ball_px = ball_radius_mm / mm_per_px
    parts = []
    ref_hwm = reference.transpose(1, 2, 0, 3)  # (H, W, P, C)

    def add(mask, normals, press, contact, img, radial=None):
        rr, cc = np.nonzero(mask)
        parts.append((img[rr, cc], ref_hwm[rr, cc], rr, cc, normals[rr, cc], np.full(len(rr), press),
                      np.full(len(rr), contact), np.zeros(len(rr)) if radial is None else radial[rr, cc]))

    flat_n = np.zeros((h, w, 3))
    flat_n[..., 2] = 1.0
    add(grid, flat_n, -1, False, ref_hwm)
    for k, circ in enumerate(circles):
        if not circ.accepted:
            continue
        img = frames[k].transpose(1, 2, 0, 3)
        cx, cy = circ.center_xy
        cap = sphere_cap((h, w), (cy, cx), circ.contact_radius_px, ball_radius_mm, mm_per_px)
        dist = np.hypot(cols - cx, rows - cy)
        margin = max(shrink_px, rim_fraction * circ.contact_radius_px)
        add(dist < circ.contact_radius_px - margin, cap.normals, k, True, img,
            dist / max(circ.contact_radius_px, 1e-9))
        add(grid & (dist > flat_outside * ball_px), flat_n, k, False, img)
    I, R, rr, cc, n, pr, ct, rad = (np.concatenate(x) for x in zip(*parts))
    s = Samples(I.astype(np.float32), R.astype(np.float32), rr, cc, n, pr, ct.astype(bool), (h, w), rad, frames,
                reference)
    if saturation is not None:
        s = s.subset((s.intensities < saturation).all(axis=(1, 2)))
    if exclude is not None:
        s = s.subset(~np.asarray(exclude, bool)[s.rows, s.cols])
    return s
