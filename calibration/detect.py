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
   sigmas), has no consistent circle (inlier fraction, or a circle more than ``peak_reach``
   radii from where the press changed the image most: a ring elsewhere, the press itself over
   the border), lies mostly over the border (less than ``min_rim_inside``, half, of its rim at
   least ``border_margin_px`` inside the image: a half circle still pins the circle) or is far
   larger or smaller than the ball; clamp the contact radius to ``clamp_fraction`` of the ball
   radius (a contact disc cannot exceed the ball).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import ndimage

__all__ = ["Circle", "DetectOptions", "detect_contacts", "detect_press", "difference_image", "drift_settings",
           "recorded_drift", "rim_inside", "shrink", "work_scale"]


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
    """Knobs of :func:`detect_press`.

    Lengths in pixels are pixels of the *working image*: the frames shrunk (OpenCV area
    averaging) so that the ball radius is at most ``work_ball_radius_px`` (frames whose ball
    is smaller are used as they are). Every scale of the search then follows from the ball:
    a 1280 x 960 frame and a 160 x 120 one are searched alike, and the averaging removes most
    JPEG noise and column stripes before any edge is looked for.
    """

    blur_sigma_px: float = 1.0
    work_ball_radius_px: float = 24.0
    edge_level: float = 0.8
    num_rays: int = 120
    ray_step_px: float = 0.2
    ransac_iterations: int = 200
    ransac_tol_px: float = 1.0
    min_inlier_fraction: float = 0.5
    soft_refit: bool = True
    faint_snr: float = 8.0
    #: A circle is kept only if the press's strongest change lies within this many radii of its
    #: centre (plus 2 px).
    peak_reach: float = 2.0
    border_margin_px: float = 1.0
    #: A circle with less of its rim inside the image is refused. Half pins a circle: on virtual
    #: sensors the presses with 50-75 % of the rim inside were found within 0.2-3.4 px (docs/calibration.md).
    min_rim_inside: float = 0.5
    clamp_fraction: float = 0.95
    max_radius_fraction: float = 1.5
    min_radius_fraction: float = 0.1
    #: The drift removed from each press before detection, sampling and evaluation
    #: (:mod:`pipeline.normals.drift`). ``gain_offset`` (constants per channel) by default; a
    #: sensor profile may name another (the DIGIT's: ``field``, a gain and an offset quadratic in
    #: the image position), and ``calibrate --drift`` any. Measured on six splits of the real
    #: presses (docs/calibration.md, "Drift"): ``field`` holds the DIGIT's fitted ball radius
    #: within 5 % on five of six (``gain_offset``: two), but the shared GelSight's fixed split,
    #: which the fixed-split targets' 3 % bound is set on, goes from 2.3 to 4.8 %.
    drift: str = "gain_offset"
    drift_degree: int = 2
    stripes: bool = False
    seed: int = 0
    #: After the edge detector, re-find every press's contact as the cap that best explains its
    #: colour change under a forward model fitted on the presses (:mod:`calibration.shading_fit`):
    #: what finds the contacts of soft gels, whose brightest change is a highlight at one rim,
    #: and of gels whose markers move. The edge circle stays where it explains the change about
    #: as well.
    shading: bool = True


def drift_settings(options: "DetectOptions") -> dict[str, Any]:
    """The drift a calibration removed, as it records it (``circle_settings``): ``drift`` and ``drift_degree``.

    >>> drift_settings(DetectOptions()) == {"drift": DetectOptions.drift, "drift_degree": DetectOptions.drift_degree}
    True
    """
    return {"drift": options.drift, "drift_degree": int(options.drift_degree)}


def recorded_drift(circle_settings: dict[str, Any]) -> "DetectOptions":
    """Detection options that remove the drift a calibration recorded (:func:`drift_settings`).

    A calibration written before the drift model was recorded removed ``gain_offset``.

    >>> recorded_drift({}).drift, recorded_drift({"drift": "field", "drift_degree": 1}).drift_degree
    ('gain_offset', 1)
    """
    return DetectOptions(drift=str(circle_settings.get("drift", "gain_offset")),
                         drift_degree=int(circle_settings.get("drift_degree", 2)))


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


def work_scale(ball_radius_px: float, options: DetectOptions | None = None) -> float:
    """Factor (<= 1) by which :func:`detect_press` shrinks the frames: ball radius at most ``work_ball_radius_px``.

    Examples
    --------
    >>> work_scale(16.0), round(work_scale(112.8), 4)
    (1.0, 0.2128)
    """
    opt = options or DetectOptions()
    return float(min(1.0, opt.work_ball_radius_px / float(ball_radius_px)))


def shrink(images: np.ndarray, scale: float) -> np.ndarray:
    """``(..., H, W, C)`` images shrunk by ``scale`` (OpenCV area averaging), float32; unchanged at 1.

    A working pixel ``j`` covers original pixels ``[j / scale, (j + 1) / scale)``: its centre is
    original pixel ``(j + 0.5) / scale - 0.5`` (:func:`to_original`).
    """
    import cv2

    a = np.asarray(images, np.float32)
    if scale >= 1.0:
        return a
    h, w, c = a.shape[-3:]
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    flat = a.reshape(-1, h, w, c)
    out = np.stack([cv2.resize(im, size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0], c) for im in flat])
    return out.reshape(a.shape[:-3] + (size[1], size[0], c))


def _fit_circle(x: np.ndarray, y: np.ndarray, start=None, soft_scale: float | None = None
                ) -> tuple[float, float, float]:
    """Algebraic fit (scikit-image ``CircleModel``) refined geometrically (``scipy.optimize.least_squares``
    on the orthogonal distances: the algebraic fit is biased when the points cover part of the circle).

    With ``start`` and ``soft_scale``: only the geometric fit, over every point with a Cauchy
    loss of that scale (points beyond it count less and less), so that the circle does not jump
    when a point crosses a hard inlier threshold.
    """
    from scipy.optimize import least_squares
    from skimage.measure import CircleModel

    pts = np.stack([x, y], axis=1).astype(np.float64)
    if start is None:
        model = CircleModel.from_estimate(pts)
        if not model:
            raise np.linalg.LinAlgError(f"no circle through {len(pts)} points")
        start = np.r_[model.center, model.radius]

    def dist(v):
        return np.hypot(pts[:, 0] - v[0], pts[:, 1] - v[1]) - v[2]

    if soft_scale is None:
        fit = least_squares(dist, np.asarray(start, np.float64), method="lm")
    else:
        fit = least_squares(dist, np.asarray(start, np.float64), loss="cauchy", f_scale=soft_scale)
    return float(fit.x[0]), float(fit.x[1]), float(abs(fit.x[2]))


def _ransac_inliers(x: np.ndarray, y: np.ndarray, tol: float, iterations: int, seed: int) -> np.ndarray:
    """Inliers of scikit-image's RANSAC with its ``CircleModel`` (seeded)."""
    from skimage.measure import CircleModel, ransac

    pts = np.stack([x, y], axis=1).astype(np.float64)
    model, inl = ransac(pts, CircleModel, min_samples=3, residual_threshold=tol, max_trials=iterations,
                        stop_probability=0.999, rng=seed)
    return np.zeros(len(x), bool) if model is None or inl is None else np.asarray(inl, bool)


def _edge_points(diff, cx, cy, r_max, opt: DetectOptions):
    h, w = diff.shape
    ang = np.linspace(0.0, 2 * np.pi, opt.num_rays, endpoint=False)
    rs = np.arange(0.0, r_max, opt.ray_step_px)
    X = cx + np.cos(ang)[:, None] * rs
    Y = cy + np.sin(ang)[:, None] * rs
    inside = (X >= 0) & (X <= w - 1) & (Y >= 0) & (Y <= h - 1)
    prof = ndimage.map_coordinates(diff, [Y, X], order=1, mode="nearest")
    peak_lim = int(len(rs) * 0.65)  # the rim lies within ~1.3 search radii of the centre
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


@dataclass
class _Found:
    """A circle in working-image pixels, before it is scaled back (``accepted`` and ``reason`` final)."""

    cx: float
    cy: float
    r: float
    quality: float
    accepted: bool
    reason: str
    snr: float
    residual: float
    located: bool  # the position means something (a blob was found), even if rejected


def _coarse_blob(diff: np.ndarray, med: float, ball_px: float, opt: DetectOptions):
    """Where the press is, roughly: ``(cx, cy, r)`` of the disc whose mean difference most
    exceeds that of the ring around it, times its radius (radii from ``min_radius_fraction`` to
    1.2 ball radii).

    A disc template (OpenCV ``filter2D`` box sums), not the brightest pixel (a specular glint
    or a saturated LED spot can outshine the rim) nor a thresholded region: where the gel is
    flat again at the apex the difference vanishes, and on many sensors that dark spot or line
    cuts the contact's disc open or in two; a disc covers both halves.
    """
    import cv2

    d = (diff - med).astype(np.float32)
    best = (-np.inf, 0.0, 0.0, 0.0)
    for r in np.geomspace(max(1.0, opt.min_radius_fraction * ball_px), 1.2 * ball_px, 10):
        ro = 1.5 * r
        n = int(np.ceil(ro))
        yy, xx = np.mgrid[-n:n + 1, -n:n + 1]
        dist = np.hypot(yy, xx)
        inner = (dist <= r).astype(np.float32)
        ring = ((dist > r) & (dist <= ro)).astype(np.float32)
        kernel = inner / inner.sum() - ring / max(ring.sum(), 1.0)
        # Contrast times the radius: the matched filter's signal to white noise (mean times the
        # square root of the pixel count), which peaks at the size of a uniform disc.
        score = cv2.filter2D(d, -1, kernel * r, borderType=cv2.BORDER_CONSTANT)
        at = np.unravel_index(int(np.argmax(score)), score.shape)
        if score[at] > best[0]:
            best = (float(score[at]), float(at[1]), float(at[0]), float(r))
    return best[1], best[2], best[3]


def _search(diff: np.ndarray, ball_px: float, opt: DetectOptions, quiet: np.ndarray | None = None) -> _Found:
    """Find the contact circle in a (working-scale, blurred) difference image; its background
    level and noise from the ``quiet`` pixels (all when None)."""
    bg = diff if quiet is None or quiet.sum() < 0.25 * quiet.size else diff[quiet]
    med = float(np.median(bg))
    sigma = float(1.4826 * np.median(np.abs(bg - med))) + 1e-6
    peak_at = np.unravel_index(int(np.argmax(diff)), diff.shape)
    snr = (float(diff[peak_at]) - med) / sigma

    def reject(reason, cx=float(peak_at[1]), cy=float(peak_at[0]), r=0.0, q=0.0, res=0.0, located=False):
        return _Found(cx, cy, r, q, False, reason, snr, res, located)

    if snr < opt.faint_snr:
        return reject(f"too faint: peak contrast {snr:.1f} noise sigmas < {opt.faint_snr}")
    cx, cy, r = _coarse_blob(diff, med, ball_px, opt)
    r_max = min(2.0 * ball_px, max(2.5 * r, 0.5 * ball_px))
    inl_frac, res = 0.0, 0.0
    for _ in range(2):
        xs, ys = _edge_points(diff, cx, cy, r_max, opt)
        if len(xs) < max(8, opt.num_rays // 4):
            return reject(f"no clear circle: only {len(xs)} of {opt.num_rays} rays found an edge", cx, cy, r,
                          located=True)
        inl = _ransac_inliers(xs, ys, opt.ransac_tol_px, opt.ransac_iterations, opt.seed)
        inl_frac = inl.sum() / len(xs)  # rays that left the image found no edge and do not vote
        if inl.sum() < 3:
            return reject("no clear circle: RANSAC found no consensus", cx, cy, r, located=True)
        try:
            start = _fit_circle(xs[inl], ys[inl])
            cx, cy, r = _fit_circle(xs, ys, start, opt.ransac_tol_px) if opt.soft_refit else start
        except np.linalg.LinAlgError:
            return reject("no clear circle: the edge points do not determine a circle", cx, cy, r, located=True)
        res = float(np.sqrt(np.mean((np.hypot(xs[inl] - cx, ys[inl] - cy) - r) ** 2)))
    quality = float(inl_frac * min(1.0, snr / (2.0 * opt.faint_snr)))
    if inl_frac < opt.min_inlier_fraction:
        return reject(f"no clear circle: {inl_frac:.0%} of rays agree (< {opt.min_inlier_fraction:.0%})",
                      cx, cy, r, quality, res, True)
    off = float(np.hypot(peak_at[1] - cx, peak_at[0] - cy))
    if off > opt.peak_reach * r + 2.0:
        # The press's strongest change lies far outside the circle: the circle is something else
        # (a ring of moved dots, a speck) and the press itself is elsewhere, e.g. over the border.
        return reject(f"no clear circle: the strongest change ({peak_at[1]}, {peak_at[0]}) lies {off:.0f} px from the "
                      f"circle found ({cx:.0f}, {cy:.0f}, r {r:.0f} px)", cx, cy, r, quality, res, True)
    return _Found(cx, cy, r, quality, True, "ok", snr, res, True)


def rim_inside(shape: tuple[int, int], center_xy, radius_px: float, margin_px: float = 0.0) -> float:
    """Fraction of a circle's rim that lies inside the image (at least ``margin_px`` from its edge).

    Examples
    --------
    >>> rim_inside((100, 100), (50.0, 50.0), 10.0), round(rim_inside((100, 100), (0.0, 50.0), 10.0), 2)
    (1.0, 0.5)
    """
    h, w = shape
    t = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    x = center_xy[0] + radius_px * np.cos(t)
    y = center_xy[1] + radius_px * np.sin(t)
    m = margin_px
    return float(np.mean((x >= m) & (x <= w - 1 - m) & (y >= m) & (y <= h - 1 - m)))


def _verdict(c: _Found, shape: tuple[int, int], ball_radius_px: float, opt: DetectOptions) -> Circle:
    """The rules on a circle in original pixels: border, size; the clamp of the contact radius."""
    cx, cy, r = c.cx, c.cy, c.r

    def circle(accepted, reason):
        return Circle((float(cx), float(cy)), float(r), float(min(r, opt.clamp_fraction * ball_radius_px)),
                      float(c.quality), accepted, reason, float(c.snr), float(c.residual))

    if not c.accepted:
        return circle(False, c.reason)
    inside = rim_inside(shape, (cx, cy), r, opt.border_margin_px)
    if inside < opt.min_rim_inside:
        return circle(False, f"touches the border: only {inside:.0%} of its rim lies inside the image (< "
                             f"{opt.min_rim_inside:.0%}; circle ({cx:.1f}, {cy:.1f}) r {r:.1f} px): press further "
                             "from the edge")
    if r > opt.max_radius_fraction * ball_radius_px:
        return circle(False, f"larger than the ball: r {r:.1f} px > {opt.max_radius_fraction} x ball radius "
                             f"{ball_radius_px:.1f} px (check --ball-radius and --mm-per-px)")
    if r < opt.min_radius_fraction * ball_radius_px:
        return circle(False, f"far smaller than the ball: r {r:.1f} px < {opt.min_radius_fraction} x ball radius "
                             f"{ball_radius_px:.1f} px (a speck, not a press? check --ball-radius and --mm-per-px)")
    notes = [] if inside >= 1.0 else [f"{inside:.0%} of its rim inside the image"]
    limit = opt.clamp_fraction * ball_radius_px
    if r > limit:
        notes.append(f"contact radius clamped from {r:.2f} to {limit:.2f} px ({opt.clamp_fraction} x ball radius)")
    return circle(True, "; ".join(notes) or "ok")


def detect_press(frames: np.ndarray, reference: np.ndarray, ball_radius_px: float,
                 options: DetectOptions | None = None, *, exclude: np.ndarray | None = None) -> Circle:
    """Detect the contact circle of one press.

    Parameters
    ----------
    frames, reference : ndarray, shape (P, H, W, C)
        The press under each pattern and the no-contact reference (linear values).
    ball_radius_px : float
        Ball radius in pixels (``ball_radius_mm / mm_per_px``): every scale of the search
        follows from it.
    options : DetectOptions, optional
    exclude : ndarray, shape (H, W), bool, optional
        Pixels left out of the drift fit (printed markers).

    Returns
    -------
    Circle
        Always a circle record (original pixels); ``accepted`` is False with a ``reason`` for
        rejected presses.

    Examples
    --------
    >>> from calibration.synthetic import synthetic_sphere_capture
    >>> cap, tr = synthetic_sphere_capture((40, 50), centers_rc=[(20.0, 24.0)], radii_px=[9.0],
    ...                                    ball_radius_mm=1.2, num_leds=3)
    >>> c = detect_press(cap.frames[0], cap.reference, 12.0)
    >>> c.accepted, abs(c.center_xy[0] - 24.0) < 1, abs(c.center_xy[1] - 20.0) < 1
    (True, True, True)
    """
    from pipeline.normals.drift import contact_exclusion, fit_drift

    opt = options or DetectOptions()
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim != 4 or frames.shape != np.shape(reference):
        raise ValueError(f"detect_press: frames and reference must both be (P, H, W, C), got {frames.shape} and "
                         f"{np.shape(reference)}")
    if not ball_radius_px > 0:
        raise ValueError(f"detect_press: ball_radius_px must be > 0, got {ball_radius_px}")
    s = work_scale(ball_radius_px, opt)
    f_w, ref_w = shrink(frames, s), shrink(reference, s)
    ball_w = ball_radius_px * s
    ex_w = quiet = None
    if exclude is not None:
        ex_w = shrink(np.asarray(exclude, np.float32)[None, :, :, None], s)[0, :, :, 0] > 0
        # The noise is measured two pixels away from the dots: a dot's blurred edge, or a dot the
        # press moved, leaves a ring in the difference image that is not the camera's noise.
        near = ndimage.binary_dilation(np.asarray(exclude, bool), iterations=2).astype(np.float32)
        quiet = ~(shrink(near[None, :, :, None], s)[0, :, :, 0] > 0)
    found = None
    for _ in range(2 if opt.drift != "none" else 1):
        # Pass 1: the drift fitted on every pixel (trimmed); pass 2: outside the contact found.
        ex = ex_w
        if found is not None and found.located:
            disc = contact_exclusion(ref_w.shape[1:3], (found.cx, found.cy), found.r, ball_w)
            ex = disc if ex is None else ex | disc
        drift = fit_drift(f_w, ref_w, ex, model=opt.drift, degree=opt.drift_degree, stripes=opt.stripes)
        found = _search(difference_image(drift.remove(f_w), ref_w, opt.blur_sigma_px), ball_w, opt, quiet)
    to_orig = (lambda v: (v + 0.5) / s - 0.5) if s < 1 else (lambda v: v)
    full = _Found(to_orig(found.cx), to_orig(found.cy), found.r / s, found.quality, found.accepted, found.reason,
                  found.snr, found.residual / s, found.located)
    return _verdict(full, frames.shape[1:3], ball_radius_px, opt)


def detect_contacts(frames: np.ndarray, reference: np.ndarray, ball_radius_px: float,
                    options: DetectOptions | None = None, *, exclude: np.ndarray | None = None) -> list[Circle]:
    """:func:`detect_press` for every press of ``frames (K, P, H, W, C)``; ``exclude`` is one
    mask ``(H, W)`` for every press or one per press ``(K, H, W)`` (markers that move)."""
    frames = np.asarray(frames)
    if frames.ndim != 5:
        raise ValueError(f"detect_contacts: frames must be (K, P, H, W, C), got {frames.shape}")
    if exclude is not None and np.ndim(exclude) == 3 and len(exclude) != len(frames):
        raise ValueError(f"detect_contacts: a per-press exclude mask must be (K={len(frames)}, H, W), got "
                         f"{np.shape(exclude)}")
    per_press = exclude is not None and np.ndim(exclude) == 3
    return [detect_press(f, reference, ball_radius_px, options, exclude=exclude[k] if per_press else exclude)
            for k, f in enumerate(frames)]
