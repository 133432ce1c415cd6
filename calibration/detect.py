"""Contact detection: find the ball's contact circle in each press, with a verdict and a reason.

Per press (one ``(P, H, W, C)`` stack against the no-contact reference):

1. **Difference image**: ``sum_{p,c} |I - I_ref|``, lightly blurred; its background level and
   noise are the median and MAD over the image.
2. **Coarse blob**: of the connected regions (holes filled: the difference is an annulus, dark
   at the apex where the gel is flat) above a fraction of the peak, the one holding the most
   difference.
3. **Edge points**: rays from the centre; on each, the outermost radius where the difference
   falls to ``edge_level`` of the way from that ray's own outer baseline to its peak (per ray, because how bright the rim is depends on which light it faces), linearly
   interpolated between samples (sub-pixel).
4. **Robust circle**: RANSAC over 3-point circles (seeded), then an algebraic fit and
   Gauss-Newton geometric refinement on the inliers; steps 3-4 are repeated from the new
   centre.
5. **Rules**: reject a press that is too faint (peak contrast below ``faint_snr`` noise
   sigmas), has no consistent circle (inlier fraction), touches the border (the circle plus
   ``border_margin_px`` leaves the image) or is far larger than the ball; clamp the contact
   radius to ``clamp_fraction`` of the ball radius (a contact disc cannot exceed the ball).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

__all__ = ["Circle", "DetectOptions", "detect_press", "detect_contacts", "difference_image"]


@dataclass
class Circle:
    """One press's contact circle.

    Attributes
    ----------
    center_xy : (float, float)
        Centre ``(x = column, y = row)`` in pixels (the hand-label convention).
    radius_px : float
        Detected radius (before clamping).
    contact_radius_px : float
        Radius used for the truth: ``min(radius_px, clamp_fraction * ball radius)``.
    quality : float
        In [0, 1]: RANSAC inlier fraction (of the rays that found an edge) times a contrast factor (1 at ``2 * faint_snr``).
    accepted : bool
    reason : str
        Why the press was rejected, or notes on an accepted one (e.g. clamped radius).
    snr : float
        Peak contrast over background noise sigma.
    residual_px : float
        RMS distance of the inlier edge points to the circle.
    shift_xy : (float, float)
        How far :func:`calibration.refine.refine_centres` moved the centre from the detected
        one (px); ``(0, 0)`` when not refined.
    """

    center_xy: tuple[float, float]
    radius_px: float
    contact_radius_px: float
    quality: float
    accepted: bool
    reason: str
    snr: float = 0.0
    residual_px: float = 0.0
    shift_xy: tuple[float, float] = (0.0, 0.0)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["center_xy"] = [float(v) for v in self.center_xy]
        d["shift_xy"] = [float(v) for v in self.shift_xy]
        return d


@dataclass
class DetectOptions:
    """Knobs of :func:`detect_press` (defaults suit 8-bit frames of 100-300 px)."""

    blur_sigma_px: float = 1.0
    blob_level: float = 0.4
    edge_level: float = 0.8
    num_rays: int = 120
    ray_step_px: float = 0.2
    ransac_iterations: int = 200
    ransac_tol_px: float = 1.0
    min_inlier_fraction: float = 0.5
    faint_snr: float = 8.0
    border_margin_px: float = 1.0
    clamp_fraction: float = 0.95
    max_radius_fraction: float = 1.5
    seed: int = 0


def difference_image(frames: np.ndarray, reference: np.ndarray, blur_sigma_px: float = 1.0) -> np.ndarray:
    """``sum_{p,c} |frames - reference|`` of one press, blurred; shape ``(H, W)``.

    Parameters
    ----------
    frames, reference : ndarray, shape (P, H, W, C)

    Examples
    --------
    >>> ref = np.zeros((1, 4, 4, 3)); f = ref.copy(); f[0, 1, 2] = [1, 2, 3]
    >>> float(difference_image(f, ref, 0)[1, 2])
    6.0
    """
    frames = np.asarray(frames, dtype=np.float32)
    reference = np.asarray(reference, dtype=np.float32)
    if frames.ndim != 4 or frames.shape != reference.shape:
        raise ValueError(f"difference_image: frames and reference must both be (P, H, W, C), got {frames.shape} "
                         f"and {reference.shape}")
    d = np.abs(frames - reference).sum(axis=(0, 3))
    return ndimage.gaussian_filter(d, blur_sigma_px) if blur_sigma_px > 0 else d


def _fit_algebraic(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    # Kasa fit: x^2 + y^2 = 2 a x + 2 b y + c, linear in (a, b, c).
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    s = np.linalg.lstsq(A, x * x + y * y, rcond=None)[0]
    cx, cy = s[0] / 2.0, s[1] / 2.0
    return cx, cy, float(np.sqrt(max(s[2] + cx * cx + cy * cy, 0.0)))


def _fit_geometric(x, y, cx, cy, r, iterations: int = 10):
    # Gauss-Newton on the orthogonal distances |p - c| - r (the algebraic fit is biased when
    # points cover only part of the circle).
    for _ in range(iterations):
        dx, dy = x - cx, y - cy
        d = np.maximum(np.hypot(dx, dy), 1e-9)
        res = d - r
        J = np.stack([-dx / d, -dy / d, -np.ones_like(d)], axis=1)
        step = np.linalg.lstsq(J, -res, rcond=None)[0]
        cx, cy, r = cx + step[0], cy + step[1], r + step[2]
        if np.abs(step).max() < 1e-6:
            break
    return float(cx), float(cy), float(r)


def _ransac_circle(x, y, tol, iterations, rng):
    n = len(x)
    best = np.zeros(n, dtype=bool)
    for _ in range(iterations):
        i = rng.choice(n, 3, replace=False)
        try:
            cx, cy, r = _fit_algebraic(x[i], y[i])
        except np.linalg.LinAlgError:
            continue
        inl = np.abs(np.hypot(x - cx, y - cy) - r) < tol
        if inl.sum() > best.sum():
            best = inl
    return best


def _edge_points(diff, cx, cy, r_max, opt: DetectOptions):
    h, w = diff.shape
    ang = np.linspace(0.0, 2 * np.pi, opt.num_rays, endpoint=False)
    rs = np.arange(0.0, r_max, opt.ray_step_px)
    X = cx + np.cos(ang)[:, None] * rs
    Y = cy + np.sin(ang)[:, None] * rs
    inside = (X >= 0) & (X <= w - 1) & (Y >= 0) & (Y <= h - 1)
    prof = ndimage.map_coordinates(diff, [Y, X], order=1, mode="nearest")
    peak_lim = int(len(rs) * 0.65)  # the rim lies within ~1.3 ball radii of the centre
    xs, ys = [], []
    for a in range(len(ang)):
        p = prof[a]
        ok = inside[a]
        im = int(np.argmax(p[:peak_lim]))
        tail = p[peak_lim + (len(rs) - peak_lim) // 2:][ok[peak_lim + (len(rs) - peak_lim) // 2:]]
        if not ok[: im + 1].all() or len(tail) < 3:
            continue  # the ray leaves the image before its outer baseline: no trustworthy edge
        base = float(np.median(tail))
        level = base + opt.edge_level * (p[im] - base)
        # The outermost sample above the level (within the rim search range) and the next one
        # below it bracket the edge; the first crossing after the maximum would stop at a dip
        # inside the disc (the difference is not monotonic inside: it depends on which light
        # each tilt faces).
        above = np.nonzero((p[:peak_lim] >= level) & ok[:peak_lim])[0]
        j = int(above[-1]) + 1 if len(above) else 0
        if j <= im or j >= len(rs) or not ok[j] or p[j] >= level:
            continue
        t = (p[j - 1] - level) / max(p[j - 1] - p[j], 1e-12)
        r = rs[j - 1] + t * opt.ray_step_px
        xs.append(cx + np.cos(ang[a]) * r)
        ys.append(cy + np.sin(ang[a]) * r)
    return np.asarray(xs), np.asarray(ys)


def detect_press(frames: np.ndarray, reference: np.ndarray, ball_radius_px: float,
                 options: DetectOptions | None = None) -> Circle:
    """Detect the contact circle of one press.

    Parameters
    ----------
    frames, reference : ndarray, shape (P, H, W, C)
        The press under each pattern and the no-contact reference (linear values).
    ball_radius_px : float
        Ball radius in pixels (``ball_radius_mm / mm_per_px``).
    options : DetectOptions, optional

    Returns
    -------
    Circle
        Always a circle record; ``accepted`` is False with a ``reason`` for rejected presses.

    Examples
    --------
    >>> from calibration.synthetic import synthetic_sphere_capture
    >>> cap, tr = synthetic_sphere_capture((40, 50), centers_rc=[(20.0, 24.0)], radii_px=[9.0],
    ...                                    ball_radius_mm=1.2, num_leds=3)
    >>> c = detect_press(cap.frames[0], cap.reference, 12.0)
    >>> c.accepted, abs(c.center_xy[0] - 24.0) < 1, abs(c.center_xy[1] - 20.0) < 1
    (True, True, True)
    """
    opt = options or DetectOptions()
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim != 4:
        raise ValueError(f"detect_press: frames must be (P, H, W, C), got {frames.shape}")
    if ball_radius_px <= 0:
        raise ValueError(f"detect_press: ball_radius_px must be > 0, got {ball_radius_px}")
    diff = difference_image(frames, reference, opt.blur_sigma_px)
    h, w = diff.shape
    med = float(np.median(diff))
    sigma = float(1.4826 * np.median(np.abs(diff - med))) + 1e-6
    peak_at = np.unravel_index(int(np.argmax(diff)), diff.shape)
    snr = (float(diff[peak_at]) - med) / sigma

    def reject(reason, cx=float(peak_at[1]), cy=float(peak_at[0]), r=0.0, q=0.0, res=0.0):
        return Circle((cx, cy), r, min(r, opt.clamp_fraction * ball_radius_px), q, False, reason, snr, res)

    if snr < opt.faint_snr:
        return reject(f"too faint: peak contrast {snr:.1f} noise sigmas < {opt.faint_snr}")
    blob = diff > med + opt.blob_level * (float(diff[peak_at]) - med)
    labels, count = ndimage.label(ndimage.binary_fill_holes(blob))
    # The press is the component with the most difference in it, not the one holding the
    # single brightest pixel (a specular glint or a saturated LED spot can outshine the rim).
    mass = ndimage.sum_labels(diff - med, labels, index=np.arange(1, count + 1))
    region = labels == (1 + int(np.argmax(mass)))
    cy, cx = ndimage.center_of_mass(region)
    r = float(np.sqrt(region.sum() / np.pi))
    rng = np.random.default_rng(opt.seed)
    inl_frac, res = 0.0, 0.0
    for _ in range(2):
        xs, ys = _edge_points(diff, cx, cy, 2.0 * ball_radius_px, opt)
        if len(xs) < max(8, opt.num_rays // 4):
            return reject(f"no clear circle: only {len(xs)} of {opt.num_rays} rays found an edge", cx, cy, r)
        inl = _ransac_circle(xs, ys, opt.ransac_tol_px, opt.ransac_iterations, rng)
        inl_frac = inl.sum() / len(xs)  # rays that left the image found no edge and do not vote
        if inl.sum() < 3:
            return reject("no clear circle: RANSAC found no consensus", cx, cy, r)
        cx, cy, r = _fit_algebraic(xs[inl], ys[inl])
        cx, cy, r = _fit_geometric(xs[inl], ys[inl], cx, cy, r)
        res = float(np.sqrt(np.mean((np.hypot(xs[inl] - cx, ys[inl] - cy) - r) ** 2)))
    quality = float(inl_frac * min(1.0, snr / (2.0 * opt.faint_snr)))
    if inl_frac < opt.min_inlier_fraction:
        return reject(f"no clear circle: {inl_frac:.0%} of rays agree (< {opt.min_inlier_fraction:.0%})",
                      cx, cy, r, quality, res)
    m = opt.border_margin_px
    if cx - r < m or cy - r < m or cx + r > w - 1 - m or cy + r > h - 1 - m:
        return reject(f"touches the border: circle ({cx:.1f}, {cy:.1f}) r {r:.1f} px within {m} px of the edge",
                      cx, cy, r, quality, res)
    if r > opt.max_radius_fraction * ball_radius_px:
        return reject(f"larger than the ball: r {r:.1f} px > {opt.max_radius_fraction} x ball radius "
                      f"{ball_radius_px:.1f} px", cx, cy, r, quality, res)
    limit = opt.clamp_fraction * ball_radius_px
    reason = "ok"
    if r > limit:
        reason = f"contact radius clamped from {r:.2f} to {limit:.2f} px ({opt.clamp_fraction} x ball radius)"
    return Circle((float(cx), float(cy)), float(r), float(min(r, limit)), quality, True, reason, snr, res)


def detect_contacts(frames: np.ndarray, reference: np.ndarray, ball_radius_px: float,
                    options: DetectOptions | None = None) -> list[Circle]:
    """:func:`detect_press` for every press of ``frames (K, P, H, W, C)``."""
    frames = np.asarray(frames)
    if frames.ndim != 5:
        raise ValueError(f"detect_contacts: frames must be (K, P, H, W, C), got {frames.shape}")
    return [detect_press(f, reference, ball_radius_px, options) for f in frames]
