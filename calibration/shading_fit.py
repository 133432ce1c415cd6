"""Contacts re-found from their shading: the sphere position and radius that best explain each press's colour change.

The edge detector (:mod:`calibration.detect`) looks for where the difference image falls off.
On a soft gel whose shading is weak and broad, with a glossy highlight at one rim, the
brightest change is that highlight, and the edges it finds circle the highlight (a third of
the contact); where printed markers move with the gel, every moved dot leaves a ring in the
difference image and the rays disagree. The colour change *inside* the contact still holds
its position and size: it is what a ball of known radius pressed there looks like.

:func:`refit_by_shading` makes that the cue (detect, fit, re-detect until stable):

1. **Forward model** from the circles trusted so far: each pixel's colour change
   ``I - I_ref`` (every pattern and channel) as a linear function of the sphere cap's normal
   (cubic in its tilt ``(g_x, g_y)`` and ``1 - n_z``), each term also times the image position
   (the lights are near), fitted by least squares over the pixels around those presses (inside
   the contact: the cap's normal; outside: flat, no change). :class:`ShadingModel`.
2. **Re-detection**: every press with a located contact (accepted or not) gets the circle
   ``(x, y, r)`` that minimises the difference between its colour change and the forward
   model's prediction for a cap there (``scipy.optimize.least_squares``, the cap's border
   anti-aliased so that the cost is smooth in the circle; several starts: the edge circle and
   circles of 0.4, 0.7 and 0.9 ball radii at its centre and at the change's centre of mass).
3. The shading's circle replaces the edge circle only where the edge detector failed: it
   rejected the press for want of a clear circle or for its size, or its circle is a small
   one off to the side of the shading's (centre more than ``off_centre`` of the shading's
   radius away and radius below ``small_fraction`` of it: a highlight at one rim), or one
   shifted by more than ``shift_fraction`` of the radius (rays pulled to one side by a ring of
   moved dots, or circling inside a soft gel's broad contact), of the same size (within
   ``same_size``) or of any size while the shading's circle stays a contact (within the
   detector's ``clamp_fraction`` of the ball: a cap as wide as the ball is the gel changing
   around the contact, as on the DIGIT), and the
   shading's circle explains the change clearly better (its squared residual at most
   :attr:`ShadingOptions.keep_edge_ratio` of the edge circle's). Elsewhere the edge circle
   stays: the shading's radius follows wherever the gel changed, and a soft gel changes
   around the contact too (on the DIGIT frames the shading's circles were 40-60 % larger
   than the edges', and the models calibrated on them 8 deg worse). Presses whose colour
   change *above the camera's noise* the model explains to at least ``min_explained`` are the
   ones the next forward model is fitted on, and only they may replace an accepted edge circle;
   repeat until no circle moves by more than ``tol_px``. The noise is each press's own (from its
   neighbouring pixels' differences, :func:`noise_variance`): measured against the raw change,
   a small press on a noisy sensor could never be explained to half, however right its circle.
   A press the edge detector refused as no clear circle (rays that disagree, the strongest
   change elsewhere: rings of moved dots) needs less, ``min_rescue``: a small shallow press
   fills a few per cent of the window, and the moved dots around it keep its right circle under
   half. Such an edge circle that no other circle explains clearly better, and that explains at
   least ``min_rescue``, is accepted where it is: the shading confirms it.

The rules of :func:`calibration.detect.detect_press` (border, size, faint presses) still
hold: a faint press stays rejected for its faintness, and a circle the shading finds too close
to the border is rejected with that reason. A press whose change the model does not explain
keeps the edge detector's verdict, its reason extended by what the shading found. An accepted
edge circle near which no cap explains even ``min_support`` (5 %) of the change (once at least three
presses shaped the model) is refused: the edges found noise or a ring of moved dots there, and
the contact is elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calibration.detect import Circle, DetectOptions, rim_inside, shrink, work_scale

__all__ = ["ShadingOptions", "ShadingModel", "cap_tilt", "refit_by_shading"]


@dataclass
class ShadingOptions:
    """Knobs of :func:`refit_by_shading`."""

    iterations: int = 4
    window: float = 1.6
    min_explained: float = 0.5
    keep_edge_ratio: float = 0.85
    off_centre: float = 0.3
    small_fraction: float = 0.6
    shift_fraction: float = 0.1
    same_size: float = 0.15
    tol_px: float = 0.25
    #: Damping of the forward model's least squares, in units of its normal matrix's mean
    #: diagonal. The model has 819 terms per pattern-channel and a handful of trusted presses:
    #: lightly damped (1e-3) it fitted the few wrong circles among them as well as the right ones,
    #: and each re-detection drifted toward them (soft-look seed 3's calibration circles a median
    #: 6.7 px off; 1.4 px at 1, 1.1 px at 3, and at 10 it explained too little to trust any press;
    #: at 3 one DIGIT circle moved 10 px, at 1 every shared GelSight and DIGIT circle is unchanged).
    ridge: float = 1.0
    #: An accepted edge circle near which the best cap explains less than this share of the
    #: change above the noise is refused: no contact is there (measured on the benchmark's
    #: virtual sensors and the shared frames: the two phantom circles of the moved-marker seeds,
    #: 147 and 252 px from their contacts, 0 %; every right circle 12 % or more, on the shared
    #: GelSight 46 % and on the DIGIT 67 % or more). Plain seed 0 has one circle 15.6 px off that
    #: overlaps its contact, at 8 %: misplaced, not a phantom, and kept (refused at 10 %, the
    #: network's exact error went from 1.82 to 2.20 deg, within what another training set moves it).
    min_support: float = 0.05
    #: A press the edge detector refused as no clear circle (rays that disagree, the strongest
    #: change elsewhere: rings of moved dots) is taken on the shading's circle, or on its own edge
    #: circle confirmed, when that explains at least this share of its change above the noise;
    #: every other press needs ``min_explained``. A small, shallow press fills a few per cent of
    #: the window the share is measured over, and the moved dots around it keep its right circle
    #: under half: on the benchmark's moving-marker virtual sensors five such presses had circles
    #: 0.7-1.9 px from the true ones at 26-42 %, while every circle found 100-470 px from its
    #: contact on the moving-marker and soft sensors explained 22 % or less. Presses refused for
    #: their size (on a soft gel the edges circle a highlight) keep the half: at a quarter, five of
    #: them on the soft sensors were taken with circles 1.2-6.9 px off, and one, 2.4 px off a 9 px
    #: contact, cost soft seed 1 0.4 deg (docs/calibration.md, "Contacts found by their shading").
    min_rescue: float = 0.25


def cap_tilt(shape: tuple[int, int], cx: float, cy: float, r: float, ball_px: float, rows=None, cols=None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cap's tilt ``(g_x, g_y, w)`` at pixels (image axes: x right, y down), ``w`` the
    fraction of each pixel inside the contact (anti-aliased over one pixel), tilt 0 outside.

    Examples
    --------
    >>> gx, gy, w = cap_tilt((5, 5), 2.0, 2.0, 1.6, 4.0)
    >>> float(gx[2, 3]), float(gy[2, 3]), float(w[2, 2]), float(w[0, 0])
    (0.25, 0.0, 1.0, 0.0)
    """
    if rows is None:
        rows, cols = np.mgrid[:shape[0], :shape[1]]
    dx, dy = cols - cx, rows - cy
    d = np.hypot(dx, dy)
    w = np.clip(r - d + 0.5, 0.0, 1.0)
    # Within the contact the cap's slope; over the anti-aliased border the slope at the rim.
    scale = np.minimum(d, r) / np.maximum(d, 1e-9) / ball_px
    return dx * scale * (w > 0), dy * scale * (w > 0), w


#: Centres and width of the radial basis on the tilt (a glossy highlight is a narrow lobe there).
_RBF_GRID = np.stack(np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 9)), axis=-1).reshape(-1, 2)
_RBF_SIGMA = 0.2


def _features(gx: np.ndarray, gy: np.ndarray, w: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``(N, 273)``: cubic tilt terms and a radial basis on the tilt, each zero on flat gel, times
    ``[1, u, v]`` and weighted by the contact fraction."""
    nz = np.sqrt(np.clip(1.0 - gx * gx - gy * gy, 0.0, 1.0))
    poly = np.stack([gx, gy, gx * gx, gx * gy, gy * gy, gx ** 3, gx * gx * gy, gx * gy * gy, gy ** 3, 1.0 - nz],
                    axis=-1)
    d2 = (gx[:, None] - _RBF_GRID[:, 0]) ** 2 + (gy[:, None] - _RBF_GRID[:, 1]) ** 2
    rbf = np.exp(-d2 / (2 * _RBF_SIGMA ** 2)) - np.exp(-(_RBF_GRID ** 2).sum(1) / (2 * _RBF_SIGMA ** 2))
    t = np.concatenate([poly, rbf], axis=1) * w[:, None]
    return np.concatenate([t, t * u[:, None], t * v[:, None]], axis=1)


class ShadingModel:
    """The forward model of step 1: colour change from the cap's tilt and the image position."""

    def __init__(self, shape: tuple[int, int], ridge: float = 1.0):
        self.shape = shape
        self.ridge = ridge
        self.coef: np.ndarray | None = None

    def uv(self, rows, cols):
        h, w = self.shape
        return 2.0 * cols / max(w - 1, 1) - 1.0, 2.0 * rows / max(h - 1, 1) - 1.0

    def fit(self, changes: list[np.ndarray], rows: list[np.ndarray], cols: list[np.ndarray], circles, ball_px: float):
        """Least squares over the pixels given (per press: change ``(N, M)``, their rows and columns, ``(x, y, r)``)."""
        A, B = [], []
        for d, rr, cc, (cx, cy, r) in zip(changes, rows, cols, circles):
            gx, gy, w = cap_tilt(self.shape, cx, cy, r, ball_px, rr, cc)
            u, v = self.uv(rr, cc)
            A.append(_features(gx, gy, w, u, v))
            B.append(d)
        a, b = np.concatenate(A), np.concatenate(B)
        lhs = a.T @ a
        lhs += self.ridge * np.trace(lhs) / len(lhs) * np.eye(len(lhs))
        self.coef = np.linalg.solve(lhs, a.T @ b)
        return self

    def predict(self, rows, cols, cx, cy, r, ball_px) -> np.ndarray:
        gx, gy, w = cap_tilt(self.shape, cx, cy, r, ball_px, rows, cols)
        u, v = self.uv(rows, cols)
        return _features(gx, gy, w, u, v) @ self.coef


@dataclass
class _Press:
    """One press at working scale: its change around the contact, where it lies, and the drift
    left in it (per pattern and channel a gain on the reference and an offset, projected out of
    every residual: the drift removed before was fitted around the edge detector's circle)."""

    change: np.ndarray  # (N, M)
    rows: np.ndarray
    cols: np.ndarray
    ref: np.ndarray  # (N, M)
    noise_var: np.ndarray | None = None  # (M,) per-pixel noise variance of the change

    def __post_init__(self):
        one = np.ones(len(self.ref))
        self.X = [np.stack([one, self.ref[:, m]], axis=1) for m in range(self.ref.shape[1])]
        self.pinv = [np.linalg.pinv(x) for x in self.X]
        self.energy = float((self.project(self.change) ** 2).sum())
        # What no circle can explain: the pixels' noise (two drift terms per column projected out).
        self.noise = 0.0 if self.noise_var is None else float(max(len(self.ref) - 2, 0) * self.noise_var.sum())

    def explained(self, cost: float) -> float:
        """The fraction of the change above the noise that a circle of this ``cost`` explains (0 when
        the change is not clearly above the noise: at most twice its energy)."""
        signal = self.energy - self.noise
        if signal <= self.noise:
            return 0.0
        return float(1.0 - np.clip((cost - self.noise) / signal, 0.0, 1.0))

    def project(self, res: np.ndarray) -> np.ndarray:
        """``res (N, M)`` without its best fit of the drift terms, per column."""
        out = np.array(res, np.float64)
        for m, (x, pi) in enumerate(zip(self.X, self.pinv)):
            out[:, m] -= x @ (pi @ out[:, m])
        return out


def noise_variance(change_img: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per column, the variance of one pixel's noise in ``change_img (H, W, M)``: from the
    differences of horizontal neighbours (both valid), whose median square is robust to the
    contact's own shading (a small part of the image) and twice the noise variance times the
    median of a chi-square with one degree of freedom (0.4549)."""
    both = valid[:, 1:] & valid[:, :-1]
    d = (change_img[:, 1:] - change_img[:, :-1])[both]
    if len(d) < 20:
        return np.zeros(change_img.shape[-1])
    return np.median(np.asarray(d, np.float64) ** 2, axis=0) / (2 * 0.4549)


def _window(change_img: np.ndarray, ref_img: np.ndarray, valid: np.ndarray, cx, cy, radius,
            noise_var: np.ndarray | None = None) -> _Press:
    h, w = valid.shape
    cx, cy = float(np.clip(cx, 0, w - 1)), float(np.clip(cy, 0, h - 1))
    r0, r1 = max(0, int(cy - radius)), min(h, int(np.ceil(cy + radius)) + 1)
    c0, c1 = max(0, int(cx - radius)), min(w, int(np.ceil(cx + radius)) + 1)
    step = 2 if radius > 24 else 1  # every other pixel of a large window: the cost's shape is the same
    rows, cols = np.mgrid[r0:r1:step, c0:c1:step]
    keep = valid[r0:r1:step, c0:c1:step] & (np.hypot(rows - cy, cols - cx) <= radius)
    rows, cols = rows[keep].astype(np.float64), cols[keep].astype(np.float64)
    ri, ci = rows.astype(int), cols.astype(int)
    return _Press(change_img[ri, ci].astype(np.float64), rows, cols, ref_img[ri, ci].astype(np.float64), noise_var)


def _fit_press(model: ShadingModel, p: _Press, starts, ball_px: float) -> tuple[tuple[float, float, float], float]:
    """The circle minimising the squared difference between change and prediction: ``((x, y, r), cost)``."""
    from scipy.optimize import least_squares

    lo, hi = 0.1 * ball_px, 0.99 * ball_px
    h, w = model.shape
    if len(p.rows) < 20:
        return None, np.inf

    def res(x):
        return p.project(p.change - model.predict(p.rows, p.cols, x[0], x[1], x[2], ball_px)).ravel()

    cand = sorted((_cost(model, p, (x, y, float(np.clip(r, lo, hi))), ball_px), (x, y, r)) for x, y, r in starts)
    best, best_cost = None, np.inf
    for _, s in cand[:2]:
        x0 = np.array([s[0], s[1], float(np.clip(s[2], lo * 1.01, hi * 0.99))])
        try:
            x0[:2] = np.clip(x0[:2], [-0.5 * ball_px, -0.5 * ball_px], [w - 1 + 0.5 * ball_px, h - 1 + 0.5 * ball_px])
            fit = least_squares(res, x0, bounds=([-ball_px, -ball_px, lo], [w - 1 + ball_px, h - 1 + ball_px, hi]),
                                diff_step=1e-3,
                                max_nfev=30, x_scale=[1.0, 1.0, 1.0])
        except ValueError:
            continue
        cost = float((fit.fun ** 2).sum())
        if cost < best_cost:
            best, best_cost = (float(fit.x[0]), float(fit.x[1]), float(fit.x[2])), cost
    return best, best_cost


def _cost(model: ShadingModel, p: _Press, circle, ball_px: float) -> float:
    return float((p.project(p.change - model.predict(p.rows, p.cols, *circle, ball_px)) ** 2).sum())


def _fit_model(model: ShadingModel, wins: list[_Press], circles, ball_px: float, rounds: int = 2) -> None:
    """The forward model on these presses, alternating with each press's drift terms."""
    changes = [w.change for w in wins]
    for _ in range(rounds):
        model.fit(changes, [w.rows for w in wins], [w.cols for w in wins], circles, ball_px)
        changes = []
        for w, c in zip(wins, circles):
            res = w.change - model.predict(w.rows, w.cols, *c, ball_px)
            changes.append(w.change - (res - w.project(res)))


def refit_by_shading(frames: np.ndarray, reference: np.ndarray, circles: list[Circle], ball_radius_px: float,
                     detect: DetectOptions | None = None, options: ShadingOptions | None = None, *,
                     exclude: np.ndarray | None = None, saturation: float | None = None
                     ) -> tuple[list[Circle], dict[str, Any]]:
    """Re-find each press's contact as the cap that best explains its colour change (see the module doc).

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        Linear frames, the drift already removed.
    reference : ndarray, shape (P, H, W, C)
    circles : list of Circle
        The edge detector's (each press's start; the accepted ones shape the first model).
    ball_radius_px : float
    detect : DetectOptions, optional
        The working scale and the border and size rules.
    exclude : ndarray, shape (H, W) or (K, H, W), bool, optional
        Pixels left out (markers).
    saturation : float, optional
        Pixels at or above it in any pattern and channel are left out.

    Returns
    -------
    circles : list of Circle
        Original pixels; a circle the shading moved notes it in its ``reason``.
    report : dict
        ``iterations``, ``moved`` (presses whose circle the shading replaced), ``explained``
        (per press, the fraction of its change the final model explains; None where not fitted),
        ``max_move_px`` per iteration.
    """
    opt = options or ShadingOptions()
    det = detect or DetectOptions()
    report: dict[str, Any] = {"iterations": 0, "moved": [], "explained": [None] * len(circles), "max_move_px": []}
    trusted = [k for k, c in enumerate(circles) if c.accepted]
    s = work_scale(ball_radius_px, det)
    ball = ball_radius_px * s
    change, ref_img, valid = _working_change(frames, reference, s, exclude, saturation)
    k_all, h, w = valid.shape
    to_w = (lambda v: (v + 0.5) * s - 0.5) if s < 1 else (lambda v: v)
    to_o = (lambda v: (v + 0.5) / s - 0.5) if s < 1 else (lambda v: v)
    edge = [(to_w(c.center_xy[0]), to_w(c.center_xy[1]), max(c.radius_px * s, 0.2 * ball)) for c in circles]
    located = [k for k, c in enumerate(circles) if c.accepted or (c.radius_px > 0 and not c.reason.startswith("too faint"))]
    cur = dict(enumerate(edge))
    # A press whose edge circle was refused for its shape may have it anywhere (a ring of moved dots,
    # a glint): its start and window are the largest region that changed, not the region nearest it.
    lost = {k for k in located if not circles[k].accepted and circles[k].reason.startswith(_OVERTURNABLE)}
    support = {k: _support_circle(change[k], valid[k], ball, None if k in lost else cur[k][:2]) for k in located}
    cur.update({k: support[k] for k in lost})
    if len(trusted) < max(3, len(located) // 3):
        # Too few edge circles to shape the first model: start every press from the region that changed.
        cur.update(support)
        trusted = list(located)
        report["start"] = "the regions that changed (too few edge circles accepted)"
    if len(trusted) < 2:
        report["note"] = "fewer than two located presses: no forward model"
        return list(circles), report
    model = ShadingModel((h, w), opt.ridge)
    explained: dict[int, float] = {}
    noise = {k: noise_variance(change[k], valid[k]) for k in located}
    for it in range(opt.iterations):
        wins = {k: _window(change[k], ref_img, valid[k], cur[k][0], cur[k][1], opt.window * ball, noise[k])
                for k in located}
        _fit_model(model, [wins[k] for k in trusted], [cur[k] for k in trusted], ball)
        new, moves = dict(cur), []
        for k in located:
            win = wins[k]
            cx, cy, r = cur[k]
            com = _centre_of_change(win)
            starts = [cur[k], edge[k], support[k]] + [(x, y, f * ball) for f in (0.3, 0.45, 0.6, 0.75, 0.9)
                                          for x, y in ((cx, cy), com)]
            fit, cost = _fit_press(model, win, starts, ball)
            if fit is None:
                continue
            failed = _edge_failed(circles[k], edge[k], fit, opt, det.clamp_fraction * ball)
            keep_edge = not failed or _cost(model, win, edge[k], ball) * opt.keep_edge_ratio <= cost
            new[k] = edge[k] if keep_edge else fit
            explained[k] = win.explained(cost)
            moves.append(float(np.hypot(new[k][0] - cur[k][0], new[k][1] - cur[k][1]) + abs(new[k][2] - cur[k][2])))
        cur = new
        trusted = [k for k in located if explained.get(k, 0.0) >= opt.min_explained] or trusted
        report["iterations"] = it + 1
        report["max_move_px"].append(max(moves) / s if moves else 0.0)
        if not moves or max(moves) < opt.tol_px * s:
            break
    out = list(circles)
    for k in located:
        x, y, r = to_o(cur[k][0]), to_o(cur[k][1]), cur[k][2] / s
        report["explained"][k] = explained.get(k)
        kept = tuple(cur[k]) == tuple(edge[k]) and not _confirmed(circles[k], explained.get(k), opt)
        out[k] = circles[k] if kept else _judged(circles[k], (x, y, r), explained.get(k, 0.0),
                                                 tuple(frames.shape[2:4]), ball_radius_px, det, opt)
        if out[k].center_xy == circles[k].center_xy:  # the edge circle stands: is a contact under it?
            out[k] = _phantom(out[k], explained.get(k), len(trusted), opt)
        if not kept and out[k] is not circles[k] and \
                np.hypot(x - circles[k].center_xy[0], y - circles[k].center_xy[1]) + abs(r - circles[k].radius_px) > 0.5:
            report["moved"].append(k)
    return out, report


def _confirmed(c: Circle, explained: float | None, opt: ShadingOptions) -> bool:
    """Does the shading confirm an edge circle the detector doubted? It was refused as no clear
    circle (rays that disagree, the strongest change elsewhere: a ring of moved dots), yet no
    circle explains the press's change better than it, and it explains enough (``min_rescue``)."""
    return _doubted(c) and explained is not None and explained >= _bar(c, opt)


def _doubted(c: Circle) -> bool:
    """Did the edge detector refuse this press as no clear circle (rays that disagree, the change elsewhere)?"""
    return not c.accepted and c.reason.startswith(_DOUBTED)


def _bar(c: Circle, opt: ShadingOptions) -> float:
    """The share of its change a circle must explain to stand for the press whose edge circle is ``c``:
    ``min_rescue`` where the edge detector doubted it, ``min_explained`` elsewhere."""
    return opt.min_rescue if _doubted(c) else opt.min_explained


def _phantom(c: Circle, explained: float | None, trusted: int, opt: ShadingOptions) -> Circle:
    """The edge circle, refused where the model (shaped by three presses or more) finds no contact near it."""
    if not c.accepted or explained is None or explained >= opt.min_support or trusted < 3:
        return c
    return replace(c, accepted=False, reason=(
        f"no contact at the circle: the shading of the other presses explains {explained:.0%} of the colour "
        f"change around it (< {opt.min_support:.0%}); the edges found something else (noise, a ring of moved dots)"))


def _working_change(frames: np.ndarray, reference: np.ndarray, s: float, exclude, saturation):
    """At working scale ``s``: each press's colour change ``(K, h, w, P*C)``, the reference
    ``(h, w, P*C)`` and where a press's pixels count ``(K, h, w)`` (not saturated, not a marker)."""
    f_w, ref_w = shrink(frames, s), shrink(reference, s)[None]
    k_all, p, h, w, c = f_w.shape
    change = (f_w - ref_w).transpose(0, 2, 3, 1, 4).reshape(k_all, h, w, p * c)
    ref_img = ref_w[0].transpose(1, 2, 0, 3).reshape(h, w, p * c)
    valid = np.ones((k_all, h, w), bool)
    if saturation is not None:
        valid &= ~(f_w >= 0.98 * saturation).any(axis=(1, 4))
    if exclude is not None:
        from scipy import ndimage

        ex = np.asarray(exclude, bool)
        ex = ex[None] if ex.ndim == 2 else ex
        # A dot's blurred halo reaches past its mask: the shading is fitted 2 px clear of every dot.
        ex = ndimage.binary_dilation(ex, structure=np.ones((1, 5, 5), bool)).astype(np.float32)
        ex_w = shrink(ex[..., None], s)[..., 0] > 0
        valid &= ~ex_w
    return change, ref_img, valid


def _support_circle(change_img: np.ndarray, valid: np.ndarray, ball_px: float, near=None) -> tuple[float, float, float]:
    """A model-free start: the disc of the same area and centroid as the region that changed
    (above six noise sigmas of the change's magnitude, holes filled; the region nearest ``near``
    ``(x, y)`` when given, else the largest)."""
    from scipy import ndimage

    mag = np.sqrt((change_img ** 2).sum(axis=-1))
    mag = ndimage.gaussian_filter(np.where(valid, mag, np.median(mag)), 1.0)
    med = float(np.median(mag))
    sigma = 1.4826 * float(np.median(np.abs(mag - med))) + 1e-6
    region = ndimage.binary_fill_holes(ndimage.binary_closing(mag > med + 6 * sigma, iterations=2))
    labels, n = ndimage.label(region)
    if n == 0:
        h, w = mag.shape
        return (w - 1) / 2, (h - 1) / 2, 0.5 * ball_px
    sizes = ndimage.sum(region, labels, range(1, n + 1))
    pick = int(np.argmax(sizes)) + 1
    if near is not None:
        cy, cx = zip(*ndimage.center_of_mass(region, labels, range(1, n + 1)))
        d = np.hypot(np.asarray(cx) - near[0], np.asarray(cy) - near[1]) - np.sqrt(sizes / np.pi)
        pick = int(np.argmin(d)) + 1
    rows, cols = np.nonzero(labels == pick)
    r = float(np.clip(np.sqrt(len(rows) / np.pi), 0.2 * ball_px, 0.95 * ball_px))
    return float(cols.mean()), float(rows.mean()), r


#: The edge detector's refusal of a circle it found but doubted (rays that disagree, the strongest change elsewhere).
_DOUBTED = "no clear circle"
#: Edge-detector rejections the shading may overturn (not faint presses, not circles over the border).
_OVERTURNABLE = (_DOUBTED, "far smaller than the ball", "larger than the ball")


def _edge_failed(c: Circle, edge, fit, opt: ShadingOptions, largest_contact: float) -> bool:
    """Did the edge detector miss this contact (rejected it for its circle, drew a small circle off to the
    side, or one shifted from the shading's while that stays smaller than ``largest_contact``)?"""
    if not c.accepted:
        return c.reason.startswith(_OVERTURNABLE)
    off = np.hypot(edge[0] - fit[0], edge[1] - fit[1])
    small_aside = off > opt.off_centre * fit[2] and edge[2] < opt.small_fraction * fit[2]
    # Shifted: rays pulled to one side (a ring of moved dots, a glint), or circling inside a soft
    # gel's broad contact (soft-look seed 0: edge circles 7-25 % small and up to 8.9 px off, the
    # shading's 0.6-2.2 px). Of another size only while the shading's circle is a contact: one as
    # wide as the ball follows the gel changing around it (a DIGIT press: 14.6 px, r 75 -> 110 px).
    same = abs(edge[2] / fit[2] - 1.0) < opt.same_size
    shifted = off > opt.shift_fraction * fit[2] and (same or fit[2] <= largest_contact)
    return bool(small_aside or shifted)


def _centre_of_change(win: _Press) -> tuple[float, float]:
    e = np.sqrt((win.change ** 2).sum(axis=1))
    tot = float(e.sum())
    if tot <= 0:
        return float(win.rows.mean()), float(win.cols.mean())
    return float((e * win.cols).sum() / tot), float((e * win.rows).sum() / tot)


def _judged(edge: Circle, circle, explained: float, shape, ball_px: float, det: DetectOptions,
            opt: ShadingOptions) -> Circle:
    """The shading's circle under the detector's rules, or the edge circle when the shading explains too little."""
    x, y, r = circle
    note = f"shading explains {explained:.0%} of the colour change above the noise"
    need = _bar(edge, opt)
    if explained < need:
        return replace(edge, reason=f"{edge.reason}; {note} (< {need:.0%}): edge circle kept")
    contact = float(min(r, det.clamp_fraction * ball_px))
    moved = np.hypot(x - edge.center_xy[0], y - edge.center_xy[1])
    base = dict(center_xy=(float(x), float(y)), radius_px=float(r), contact_radius_px=contact,
                quality=max(edge.quality, float(explained)))
    inside = rim_inside(shape, (x, y), r, det.border_margin_px)
    if inside < det.min_rim_inside:
        return replace(edge, **base, accepted=False,
                       reason=f"touches the border: only {inside:.0%} of its rim lies inside the image (< "
                              f"{det.min_rim_inside:.0%}; circle found by its shading ({x:.1f}, {y:.1f}) r {r:.1f} px): "
                              "press further from the edge")
    same = moved < 0.5 and abs(r - edge.radius_px) < 0.5  # the edge circle itself
    if edge.accepted:
        reason = edge.reason if same else \
            f"{edge.reason}; moved {moved:.1f} px and r {edge.radius_px:.1f} -> {r:.1f} px by its shading ({note})"
        return replace(edge, **base, reason=reason)
    how = "confirmed" if same else "found"
    return replace(edge, **base, accepted=True,
                   reason=f"{how} by its shading ({note}); the edge detector had: {edge.reason}")
