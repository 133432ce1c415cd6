"""The contact mask: where an object touches the gel, from the colour change and the height.

What gs_sdk users call the contact mask ``C``: pixels where the frame differs from the no-contact
reference by more than the noise (a touch changes the colour), that are also raised above the
flat gel in the reconstructed height map (a colour change alone may be a shadow, a marker or
drift). Numpy in, numpy out; :func:`pipeline.workflows.reconstruct.reconstruct` writes it beside the depth
(``contact`` in ``depth.h5``, ``contact_kNNN.png``) and ``iristac live`` shows and returns it.

Colour: ``|frame - reference|`` (L2 over patterns and channels) after removing the press's
illumination drift against the reference (:data:`CONTACT_DRIFT`, fitted by the drift estimator
the normals stage uses, :mod:`pipeline.normals.drift`: a drift of the light is not a touch),
above ``color_threshold``
(default: the median change plus ``noise_sigmas`` robust standard deviations, so 8-bit and
16-bit frames need no tuning); closed and hole-filled (the difference of a pressed ball is an
annulus: its flat apex barely changes colour), specks smaller than ``min_area_px`` dropped.
Height: above the flat gel's level (the median height outside the colour mask) by
``height_threshold_mm``, or by default ``height_fraction`` of the highest point. With both, the
mask is the colour's regions that are raised (the colour gives the outline: a reconstructed
height map is smooth and often narrower or wider than the contact; a colour change that is not
raised, a shadow or a marker, is dropped), within ``grow_px`` of raised regions the colour
confirms; a raised region with hardly any colour mask but a mean colour change that stands out
from the noise (a faint touch) is taken as the height has it. Where only one of the two
is given, that one decides.
"""

from __future__ import annotations

import numpy as np

__all__ = ["contact_mask", "color_change", "capture_contact_masks", "drift_estimator", "contact_reference_level",
           "CONTACT_DRIFT"]

#: The drift model the colour change removes (:mod:`pipeline.normals.drift`): a gain and an offset
#: that vary smoothly over the image (degree 2), as vignetting and a moved light do. On the virtual
#: sensor (4 seeds x 6 presses, 120 x 160, true heights) the masks matched the true contact as well as
#: the earlier offset-only quadratic did and as a per-channel gain and offset did, better with stripes
#: and JPEG noise; on one sensor with every flaw (seed 3) a per-channel gain and offset lost a press
#: cut by the border that this keeps. Figures in docs/reconstruction.md ("Contact mask").
CONTACT_DRIFT = "field"

#: Pixels the drift is fitted on (seeded sample; every pixel when fewer).
DRIFT_SAMPLES = 2000


def drift_estimator(reference, drift: str = CONTACT_DRIFT):
    """The drift estimator :func:`color_change` fits against ``reference`` ((P, H, W, C) or
    (H, W, C), linear): built once, it serves every press of one reference (None for ``none``)."""
    from pipeline.normals.drift import DriftEstimator

    if drift == "none":
        return None
    r = np.asarray(reference, np.float32)
    return DriftEstimator(r[None] if r.ndim == 3 else r, model=drift, max_samples=DRIFT_SAMPLES)


def color_change(frames, reference, *, drift: str = CONTACT_DRIFT, estimator=None) -> np.ndarray:
    """Per-pixel colour change ``(H, W)`` of a press against the reference, drift removed.

    The press's illumination drift against the reference (``drift``: by default a gain and an
    offset per pattern and channel, :class:`pipeline.normals.drift.DriftEstimator`,
    fitted on a sample of the pixels and trimmed so that the contact drops out: a drift of the
    light between the reference and the press, not a touch) is removed first.

    Parameters
    ----------
    frames, reference : ndarray, shape (P, H, W, C) or (H, W, C)
        Linear values (dark level removed where known).
    drift : str
        A model of :data:`pipeline.normals.drift.DRIFT_MODELS` (``none``: the plain difference).
    estimator : DriftEstimator, optional
        :func:`drift_estimator` of this reference, built once for many presses (then ``drift``
        is its model).

    Returns
    -------
    ndarray, shape (H, W), float32
        L2 norm over patterns and channels of the remaining difference.

    Examples
    --------
    >>> ref = np.tile(np.linspace(60, 180, 16)[None, :, None], (12, 1, 3))
    >>> f = 1.1 * ref + 7.0                              # a global gain and offset: no change
    >>> f[5, 8] += [3.0, 4.0, 0.0]                       # one pixel changed by |(3, 4, 0)| = 5
    >>> color_change(f, ref)[5, 6:11].round().tolist()
    [0.0, 0.0, 5.0, 0.0, 0.0]
    >>> color_change(f, ref, drift="none")[5, 6:11].round().tolist()   # the drift, not removed
    [31.0, 32.0, 38.0, 35.0, 36.0]
    """
    f = np.asarray(frames, np.float32)
    r = np.asarray(reference, np.float32)
    if f.shape != r.shape or f.ndim not in (3, 4):
        raise ValueError(f"color_change: frames and reference must both be (P, H, W, C) or (H, W, C), got "
                         f"{f.shape} and {r.shape}")
    if f.ndim == 3:
        f, r = f[None], r[None]
    est = estimator if estimator is not None else drift_estimator(r, drift)
    if est is not None:
        f = est.fit(f).remove_from(f)
    d = f - r
    return np.sqrt(np.einsum("phwc,phwc->hw", d, d))


def _close_and_fill(mask: np.ndarray, radius: int) -> np.ndarray:
    """Morphological closing by a disc (edge-padded, so a region cut by the border is not eroded
    from it), then holes filled (flood fill from the outside)."""
    import cv2

    m = mask.astype(np.uint8)
    if radius > 0:
        r = int(radius)
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        m = cv2.morphologyEx(np.pad(m, r, mode="edge"), cv2.MORPH_CLOSE, k)[r:-r, r:-r]
    h, w = m.shape
    outside = np.zeros((h + 2, w + 2), np.uint8)
    outside[1:-1, 1:-1] = m
    flood = outside.copy()
    cv2.floodFill(flood, np.zeros((h + 4, w + 4), np.uint8), (0, 0), 1)
    holes = flood[1:-1, 1:-1] == 0
    return (m > 0) | holes


def contact_reference_level(reference) -> float:
    """The no-contact reference's 99th percentile (every third pixel): the scale of ``min_change``."""
    return float(np.percentile(np.asarray(reference, np.float32)[..., ::3, ::3, :], 99))


def contact_mask(frames=None, reference=None, height=None, *, color_threshold: float | None = None,
                 noise_sigmas: float = 6.0, height_threshold_mm: float | None = None, height_fraction: float = 0.05,
                 min_change: float = 0.02, peak_fraction: float = 0.3, valid=None, blur_px: float = 1.0,
                 close_px: int = 3, grow_px: int = 3, min_area_px: int = 9, drift: str = CONTACT_DRIFT,
                 estimator=None, reference_level: float | None = None) -> np.ndarray:
    """Where the object touches the gel: ``(H, W)`` bool.

    Parameters
    ----------
    frames, reference : ndarray, shape (P, H, W, C) or (H, W, C), optional
        The press and the no-contact reference (both or neither).
    height : ndarray, shape (H, W), optional
        Reconstructed height (mm, positive toward the camera: a press is a bump).
    color_threshold : float, optional
        Colour change that counts as touch (same units as the frames), after a Gaussian blur
        of ``blur_px``; default: median change + ``noise_sigmas`` x 1.4826 x MAD, at least
        ``min_change`` of the reference's 99th percentile.
    height_threshold_mm : float, optional
        Height above the flat gel that counts as touch; default ``height_fraction`` of the
        highest point above the flat gel.
    valid : ndarray of bool, shape (H, W), optional
        Pixels with a trustworthy height (a solver's mask); others are not contact by height.
    min_change, peak_fraction : float
        The automatic colour threshold is at least ``min_change`` of the reference's 99th
        percentile and ``peak_fraction`` of the way from the median change to its peak.
    blur_px, close_px, grow_px, min_area_px
        Gaussian blur of the colour change; closing radius of the colour mask; how far from a
        raised region its colour outline may reach; smallest region kept (pixels).
    drift, estimator
        The illumination drift removed from the colour change (:func:`color_change`).
    reference_level : float, optional
        :func:`contact_reference_level` of ``reference`` (what ``min_change`` scales), for callers that
        mask many frames against one reference; computed here when not given.

    Returns
    -------
    ndarray of bool, shape (H, W)

    Examples
    --------
    A press whose colour changes on an annulus and whose height is a cap of radius 4 px, a
    shadow in one corner (colour, no height) and a height artefact in another (height, no colour):

    >>> yy, xx = np.mgrid[0:24, 0:24]; r = np.hypot(xx - 10, yy - 10)
    >>> ref = np.full((24, 24, 3), 100.0)
    >>> frame = ref + np.where((r > 2) & (r < 4), 40.0, 0.0)[..., None]
    >>> frame[:4, :4] -= 50
    >>> h = np.clip(0.3 - 0.02 * r * r, 0, None)
    >>> h[19:23, 19:23] = 0.2
    >>> m = contact_mask(frame, ref, h)
    >>> int(m.sum()), bool(m[10, 10]), bool(m[1, 1]), bool(m[20, 20])
    (45, True, False, False)
    >>> bool(contact_mask(frame, ref)[1, 1]), bool(contact_mask(height=h)[20, 20])   # one cue alone
    (True, True)
    """
    if (frames is None) != (reference is None):
        raise ValueError("contact_mask: give frames and reference together (or neither)")
    if frames is None and height is None:
        raise ValueError("contact_mask: needs frames and a reference, a height map, or both")
    color = change = evidence = None
    if frames is not None:
        color, change, evidence = _color_touch(frames, reference, color_threshold, noise_sigmas, min_change,
                                               peak_fraction, blur_px, close_px, drift, estimator, reference_level)
    touch = color
    if height is not None:
        raised = _raised(height, color, valid, height_threshold_mm, height_fraction)
        touch = raised if color is None else _confirmed_outline(raised, color, change, evidence, grow_px)
    return _without_small_regions(touch, min_area_px)


def _color_touch(frames, reference, color_threshold, noise_sigmas, min_change, peak_fraction, blur_px, close_px,
                 drift, estimator, reference_level):
    """``(colour mask, blurred colour change, evidence level)``: the pixels whose change passes the
    threshold (given, else from the change's noise, :func:`contact_mask`), closed and filled, and the
    mean change that confirms a raised region."""
    from scipy import ndimage

    change = color_change(frames, reference, drift=drift, estimator=estimator)
    if blur_px > 0:
        change = ndimage.gaussian_filter(change, blur_px, mode="nearest")
    sample = change[::2, ::2]  # noise statistics from every other pixel: as good, 4x cheaper
    med = float(np.median(sample))
    sigma = 1.4826 * float(np.median(np.abs(sample - med)))
    floor = min_change * (reference_level if reference_level is not None else contact_reference_level(reference))
    if color_threshold is None:
        peak = float(np.percentile(sample, 99.9))
        color_threshold = max(med + noise_sigmas * sigma, floor, med + peak_fraction * (peak - med)) + 1e-6
    evidence = max(med + 0.5 * noise_sigmas * sigma, 0.5 * floor)
    return _close_and_fill(change > color_threshold, close_px), change, evidence


def _raised(height, color, valid, height_threshold_mm, height_fraction) -> np.ndarray:
    """The valid pixels raised above the flat gel (the median height outside the colour mask) by
    the threshold (given, else ``height_fraction`` of the highest point)."""
    h = np.asarray(height, np.float64)
    if h.ndim != 2 or (color is not None and h.shape != color.shape):
        raise ValueError(f"contact_mask: height must be (H, W) like the frames, got {h.shape}")
    ok = np.isfinite(h) if valid is None else (np.asarray(valid, bool) & np.isfinite(h))
    outside = ok & (~color if color is not None else np.ones_like(ok))
    if not outside.any():
        outside = ok
    base = float(np.median(h[outside])) if outside.any() else 0.0
    h = np.where(ok, h - base, 0.0)
    if height_threshold_mm is None:
        top = float(h[color].max()) if color is not None and color.any() else float(h.max())
        height_threshold_mm = max(height_fraction * top, 0.0)
    return ok & (h > height_threshold_mm)


def _confirmed_outline(raised, color, change, evidence, grow_px) -> np.ndarray:
    """Raised regions the colour confirms (they meet the colour mask, or their mean change
    stands out from the noise); within ``grow_px`` of them the colour gives the outline, except
    where a region has hardly any colour (a faint touch): there the height does."""
    from scipy import ndimage

    hlab, hn = ndimage.label(raised)
    idx = np.arange(1, hn + 1)
    hit = np.asarray(ndimage.mean(color, hlab, idx)) if hn else np.zeros(0)
    mean = np.asarray(ndimage.mean(change, hlab, idx)) if hn else np.zeros(0)
    confirmed = np.isin(hlab, idx[(hit > 0) | (mean > evidence)])
    faint = np.isin(hlab, idx[(hit < 0.3) & (mean > evidence)])
    near = ndimage.binary_dilation(confirmed, iterations=grow_px) if grow_px > 0 else confirmed
    return (color & near) | faint


def _without_small_regions(touch: np.ndarray, min_area_px: int) -> np.ndarray:
    """``touch`` without its connected regions smaller than ``min_area_px`` pixels."""
    from scipy import ndimage

    if min_area_px > 1 and touch.any():
        labels, n = ndimage.label(touch)
        sizes = ndimage.sum_labels(touch, labels, index=np.arange(1, n + 1))
        touch = np.isin(labels, 1 + np.flatnonzero(sizes >= min_area_px))
    return touch


def capture_contact_masks(data, heights, valid=None, region=None, **options) -> np.ndarray:
    """:func:`contact_mask` of every contact instance of a capture: ``(K, H, W)`` bool.

    Parameters
    ----------
    data : mapping
        A capture's datasets: ``frames (K, P, H, W, C)``, optional ``reference (P, H, W, C)``
        (without one, the height alone decides).
    heights : ndarray, shape (K, H, W)
        Reconstructed heights (mm).
    valid : ndarray of bool, shape (K, H, W), optional
        The depth's validity masks.
    region : ndarray of bool, shape (H, W), optional
        The reconstructed pixels; nothing outside is contact.
    **options
        Passed to :func:`contact_mask`.

    Examples
    --------
    >>> f = np.full((2, 1, 12, 12, 3), 50.0); f[0, 0, 3:7, 3:7] += 40   # press 0 touches, press 1 not
    >>> h = np.zeros((2, 12, 12)); h[0, 3:7, 3:7] = 0.2
    >>> m = capture_contact_masks({"frames": f, "reference": np.full((1, 12, 12, 3), 50.0)}, h)
    >>> m.shape, bool(m[0, 4, 4]), bool(m[0, 10, 10]), int(m[1].sum())
    ((2, 12, 12), True, False, 0)
    """
    frames = data["frames"]
    ref = data.get("reference")
    heights = np.asarray(heights)
    k = heights.shape[0]
    out = np.zeros(heights.shape, bool)
    drift = options.pop("drift", CONTACT_DRIFT)
    est = None if ref is None else drift_estimator(ref, drift)
    level = None if ref is None else contact_reference_level(ref)  # one reference for every instance
    for i in range(k):
        v = None if valid is None else np.asarray(valid[i], bool)
        if ref is not None:
            out[i] = contact_mask(frames[i], ref, heights[i], valid=v, drift="none" if est is None else drift,
                                  estimator=est, reference_level=level, **options)
        else:
            out[i] = contact_mask(height=heights[i], valid=v, **options)
    if region is not None:
        out &= np.asarray(region, bool)[None]
    return out
