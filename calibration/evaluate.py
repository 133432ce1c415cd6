"""How good is a calibration on presses it never saw: ``iristac eval calibration CAL.h5 TEST.h5``.

Leave-presses-out cross-validation (:mod:`calibration.validate`) is optimistic: the held-out
presses come from the same capture whose circles, refinement and sample selection shaped the
model, and a user picks the model by that very number. This module applies every model of a
calibration to a separate *test* capture (other presses of the same sensor) and reports three
things:

- **detected truth**: the test capture's own circles from the edge detector alone
  (:func:`calibration.calibrate.find_circles` without centre refinement, a 2 px margin inside
  each circle), whatever settings the calibration under test used. No light model shapes
  this truth: refinement lets a fitted light model vote for the centres, and each model
  family then scores 3-4 degrees better against circles its own family refined (measured on
  the shared real frames, docs/calibration.md "Which truth"), so a refined truth would judge
  the models by their likeness to the refiner. Angular error on the contact pixels, invalid
  predictions counted as 90 degrees;
- **label truth** (when the test capture has ``labels/*``): the same against hand-labelled
  circles (:mod:`calibration.labels`: contact radius clamped to 0.95 of the ball), reported
  separately: hand labels carry their labeller's convention (docs/calibration.md);
- **ball fit** (:mod:`calibration.ballfit`): each press's predicted normals integrated to a
  height map (DST Poisson) and a sphere fitted to the top of the bump; its radius against the
  ball's needs no circle at all.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from calibration.ballfit import ball_fit
from calibration.detect import recorded_drift
from calibration.labels import capture_label_circles, has_labels, label_circles
from calibration.samples import Samples, collect_samples
from calibration.validate import INVALID_ERROR_DEG
from pipeline.base.capture import Capture, read_capture
from pipeline.base.errors import UserError
from pipeline.results.evaluate import angular_error_deg
from sim.geometry.shapes import cap_depth

if TYPE_CHECKING:
    from calibration.detect import Circle

__all__ = ["evaluate_calibration", "evaluate_models", "angular_stats", "label_circles", "format_report", "CV_GAP_WARN_DEG",
           "TEST_TRUTH", "exact_normals"]

#: A model whose test error and CV error differ by more than this is flagged in the report.
CV_GAP_WARN_DEG = 2.0

#: How the detected truth of a test capture is found (:func:`calibration.calibrate.find_circles`
#: arguments), the same for every calibration judged: the edge detector alone, a 2 px margin.
TEST_TRUTH = {"refine_iterations": 0, "shrink_px": 2.0, "folds": 5}


def angular_stats(errors: np.ndarray, press: np.ndarray) -> dict[str, Any]:
    """``mean_deg``, ``median_deg``, ``p90_deg``, ``invalid_fraction`` and ``per_press`` of errors.

    ``errors (N,)`` in degrees (invalid predictions already set to 90), ``press (N,)`` the
    press of each pixel.

    Examples
    --------
    >>> s = angular_stats(np.array([1.0, 3.0, 90.0]), np.array([0, 0, 1]))
    >>> s["mean_deg"], s["median_deg"], round(s["invalid_fraction"], 3), s["per_press"]["1"]["mean_deg"]
    (31.333333333333332, 3.0, 0.333, 90.0)
    """
    e = np.asarray(errors, np.float64)
    if e.size == 0:
        return {"mean_deg": None, "median_deg": None, "p90_deg": None, "invalid_fraction": None, "per_press": {}}
    per = {str(int(p)): {"mean_deg": float(e[press == p].mean()), "median_deg": float(np.median(e[press == p])),
                         "pixels": int((press == p).sum())} for p in np.unique(press)}
    return {"mean_deg": float(e.mean()), "median_deg": float(np.median(e)), "p90_deg": float(np.percentile(e, 90)),
            "invalid_fraction": float(np.mean(e >= INVALID_ERROR_DEG)), "per_press": per}


def evaluate_models(models: dict[str, Any], samples: Samples) -> dict[str, dict[str, Any]]:
    """Angular-error statistics (:func:`angular_stats`) of each model on the contact samples."""
    contact = samples.subset(samples.contact & (samples.press >= 0))
    out = {}
    if len(contact) == 0:
        return {name: angular_stats(np.array([]), np.array([])) for name in models}
    for name, model in models.items():
        n, ok = model.predict(contact)
        e = angular_error_deg(n, contact.normals)
        out[name] = angular_stats(np.where(ok & np.isfinite(e), e, INVALID_ERROR_DEG), contact.press)
        if not ok.any():
            # Every prediction invalid: 90 deg would read as a result; there is none.
            out[name].update(mean_deg=None, median_deg=None, p90_deg=None, note="no valid prediction")
    return out


#: Resamplings of the test presses behind the range of the ball fit's median |error|.
BOOTSTRAP_RESAMPLES = 2000


def _median_range(values: np.ndarray, low: float = 10.0, high: float = 90.0) -> list[float] | None:
    """Where the median of ``values`` falls when the presses are drawn again (bootstrap, seeded):
    its ``low``-``high`` percentiles, or None under 5 values.

    A median of ten presses that scatter by several per cent is itself uncertain by a few: this
    says by how much, from the presses at hand.

    >>> [round(v, 3) for v in _median_range(np.arange(1, 10) / 100)]
    [0.03, 0.07]
    """
    if values.size < 5:
        return None
    draws = np.random.default_rng(0).integers(0, values.size, (BOOTSTRAP_RESAMPLES, values.size))
    lo, hi = np.percentile(np.median(values[draws], axis=1), [low, high])
    return [float(lo), float(hi)]


def _ball_fits(models, found, ball_radius_mm: float, depths: list[float | None], level: float) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, model in models.items():
        per = []
        t = time.perf_counter()
        maps = model.normal_maps(found.frames, found.reference, markers=found.markers)
        for k in range(len(found.frames)):
            # Filled-in marker pixels are guesses (False in the mask) but good enough to integrate
            # through: treating them as flat gel would dent every cap they cross.
            usable = maps.mask[k] if maps.filled is None else maps.mask[k] | maps.filled
            c = found.circles[k]
            r = ball_fit(maps.normals[k], found.mm_per_px, ball_radius_mm, mask=usable, level=level,
                         true_depth_mm=depths[k], contact=(*c.center_xy, c.radius_px))
            per.append({"press": k, **r})
        signed = np.array([p["radius_error"] for p in per if p["radius_error"] is not None], float)
        dep = [abs(p["depth_error"]) for p in per if p["depth_error"] is not None]
        out[name] = {**_radius_summary(signed, ball_radius_mm),
                     "depth_error_median": float(np.median(dep)) if dep else None,
                     "seconds": time.perf_counter() - t, "per_press": per}
    return out


def _radius_summary(signed: np.ndarray, ball_radius_mm: float) -> dict[str, Any]:
    """The fitted presses' relative radius errors ``signed`` summed up (:func:`evaluate_calibration`'s
    ``ball_fit`` keys). The median |error| mixes the scale (the signed median) with how much
    single presses scatter: both are reported, so a user can tell them apart."""
    if not signed.size:
        return {"radius_error_median": None, "radius_mm_median": None, "radius_error_signed_median": None,
                "radius_error_spread": None, "radius_error_median_range": None, "fitted": 0}
    scale = float(np.median(signed))
    return {"radius_error_median": float(np.median(np.abs(signed))),
            "radius_mm_median": ball_radius_mm * (1.0 + scale),
            "radius_error_signed_median": scale,
            "radius_error_spread": float(1.4826 * np.median(np.abs(signed - scale))) if signed.size >= 3 else None,
            "radius_error_median_range": _median_range(np.abs(signed)),
            "fitted": int(signed.size)}


def _press_depths(cap: Capture, circles: list[Circle], ball_radius_mm: float, mm_per_px: float):
    """Each press's depth: from rendered truth when the capture has it, else from the detected radius."""
    if cap.truth and "height" in cap.truth:
        return [float(np.max(h)) for h in np.asarray(cap.truth["height"])], "truth/height maximum"
    # The detected radius, not the truth's clamped one: a visible edge at or beyond the ball's
    # radius means a press about as deep as the ball's equator (depth ~ R), whatever the truth
    # disc keeps for safety.
    return ([float(cap_depth(ball_radius_mm, c.radius_px * mm_per_px)) if c.accepted else None for c in circles],
            "R - sqrt(R^2 - a^2), a the detected contact radius capped at R")


def evaluate_calibration(calibration, test_capture, ball_radius_mm: float | None = None, *,
                         mm_per_px: float | None = None, models: list[str] | None = None, ball_level: float = 0.5,
                         refine_iterations: int | None = None, refine_model: str | None = None,
                         shrink_px: float | None = None, folds: int | None = None, circles=None,
                         markers=None, detect_options=None) -> dict[str, Any]:
    """Every model of a calibration applied to presses it never saw.

    Parameters
    ----------
    calibration : path, CalibrationResult or dict name -> model
        A calibration.h5 (:func:`calibration.stored.load_calibration`), the result of
        :func:`calibration.calibrate.calibrate`, or fitted models.
    test_capture : path or Capture
        A sphere-indentation capture of the same sensor with other presses.
    ball_radius_mm : float, optional
        Default: the calibration's ``ball_radius_mm`` attribute, then the capture's.
    mm_per_px : float, optional
        Default: the test capture's, then the calibration's.
    models : list of str, optional
        Names to evaluate (default: all in the calibration).
    ball_level : float
        Fraction of the peak height fitted by the ball check (:func:`calibration.ballfit.cap_region`).
    refine_iterations, refine_model, shrink_px, folds
        How the test capture's circles are found (:func:`calibration.calibrate.find_circles`);
        default :data:`TEST_TRUTH`, whatever the calibration's own settings: the edge detector
        alone (no light model votes for the truth), a 2 px margin. ``refine_model`` matters only
        with ``refine_iterations > 0``, and ``auto`` refines only with a traced model: name one
        (``near``, ``far``, ``mlp``) to see a refined truth (docs/calibration.md, "Which truth").
    circles : CircleFit, optional
        The test capture's circles from an earlier ``find_circles`` call with the same
        settings (reused instead of found again: benchmarks evaluate many calibrations).
    markers : None, "none", "auto", a mask image path or an (H, W) bool array
        Printed gel markers; None: the test capture's own, else the calibration's.
    detect_options : DetectOptions, optional
        How the test presses' circles are found and their drift removed
        (:class:`calibration.detect.DetectOptions`; ``drift="none"`` keeps the frames as
        recorded, as ``iristac reconstruct`` reads them). Default: the drift model the
        calibration removed from its own presses (:func:`calibration.detect.recorded_drift`).

    Returns
    -------
    dict
        Exactly ``presses``, ``accepted``, ``models`` (name -> ``mean_deg``, ``median_deg``,
        ``p90_deg``, ``invalid_fraction``, ``per_press``, against the detected truth; plus
        ``cv_mean_deg`` from the calibration, ``cv_truth`` (what the calibration was fitted and
        cross-validated on: ``detected``, ``labels`` or ``given`` circles), ``cv_gap_deg`` = test
        minus CV on the same kind of truth (the labels' for a calibration on labels) and
        ``note``, set when the gap exceeds :data:`CV_GAP_WARN_DEG`; ``mean_deg`` etc. None when no
        prediction is valid; ``problems``: why the model's figures are not results, from its
        calibration's verdict (:func:`calibration.gate.model_problems`) and from the test presses
        (no valid prediction, a ball fit more than
        :data:`calibration.gate.MAX_BALL_RADIUS_ERROR` off or no round bump), and ``usable`` = no
        problems), ``truth`` (``detected``: how the circles were found, the circles and
        ``drift``, the model removed from the test presses; ``labels`` when the capture has hand
        labels: the same statistics per model against them) and ``ball_fit`` (name -> ``radius_error_median`` and
        ``depth_error_median`` (medians of the absolute relative errors), ``radius_mm_median``,
        ``radius_error_signed_median`` (the median radius's relative error: the scale),
        ``radius_error_spread`` (1.4826 x the median absolute deviation of the signed errors: how
        much single presses scatter; None under 3 fits), ``radius_error_median_range`` (10-90 %
        of the median |error| over bootstrap draws of the fitted presses; None under 5),
        ``fitted`` (presses with a radius), ``per_press``).
    """
    from calibration.calibrate import find_circles

    loaded, meta = _calibration_models(calibration, models)
    cap = read_capture(test_capture) if not isinstance(test_capture, Capture) else test_capture
    src = str(test_capture) if not isinstance(test_capture, Capture) else "test capture"
    radius, mm = _test_scale(cap, src, meta, ball_radius_mm, mm_per_px)
    _check_compatible(loaded, cap, src)
    if markers is None and cap.markers is None:
        markers = meta.get("markers")
    cs = meta.get("circle_settings") or {}
    if detect_options is None and "circle_settings" in meta:
        # The test presses lose the drift the calibration's presses lost: a model fitted to
        # field-corrected contrasts is judged on field-corrected contrasts.
        detect_options = recorded_drift(cs)
    refine_iterations = TEST_TRUTH["refine_iterations"] if refine_iterations is None else int(refine_iterations)
    refine_model = "auto" if refine_model is None else refine_model
    shrink_px = TEST_TRUTH["shrink_px"] if shrink_px is None else float(shrink_px)
    folds = TEST_TRUTH["folds"] if folds is None else int(folds)
    found = circles if circles is not None else find_circles(
        cap, radius, mm, refine_iterations=refine_iterations, refine_model=refine_model, shrink_px=shrink_px,
        folds=folds, markers=markers, strict=False, detect_options=detect_options)
    detected = int(sum(c.accepted for c in found.circles))
    # With no test press detected the label truth (when there is one) and the ball fit, which
    # needs no circle, still judge the calibration.
    det = evaluate_models(loaded, found.samples)
    truth: dict[str, Any] = {"detected": _detected_truth(found, shrink_px, detected, has_labels(cap))}
    if has_labels(cap):
        truth["labels"] = _label_truth(loaded, cap, found, radius, shrink_px, src)
    _add_cv_gaps(det, meta, truth, cs.get("circles", "detected"))
    depths, depth_method = _press_depths(cap, found.circles, radius, found.mm_per_px)
    fits = _ball_fits(loaded, found, radius, depths, ball_level)
    for v in fits.values():
        v["depth_truth"] = depth_method
    for name, stats in det.items():
        stats["problems"] = _model_problems((meta.get("validation") or {}).get(name), stats, fits[name])
        stats["usable"] = not stats["problems"]
    return {"presses": int(len(found.circles)), "accepted": detected,
            "models": det, "truth": truth, "ball_fit": fits}


def _calibration_models(calibration, models: list[str] | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(name -> model, meta)`` of a calibration file, a ``CalibrationResult`` or a dict of
    models (``meta`` empty), keeping only ``models`` when given."""
    from calibration.stored import load_calibration

    meta: dict[str, Any] = {}
    if isinstance(calibration, (str, Path)):
        loaded, meta = load_calibration(calibration)
        order = list(meta.get("models") or [])  # the order calibrate fitted them in
        loaded = dict(sorted(loaded.items(), key=lambda kv: order.index(kv[0]) if kv[0] in order else len(order)))
    elif hasattr(calibration, "models") and hasattr(calibration, "reports"):  # a CalibrationResult
        loaded = dict(calibration.models)
        meta = {"validation": calibration.reports, "ball_radius_mm": calibration.ball_radius_mm,
                "mm_per_px": calibration.mm_per_px, "markers": calibration.markers,
                "circle_settings": calibration.meta.get("circle_settings", {})}
    else:
        loaded = dict(calibration)
    if models:
        missing = [m for m in models if m not in loaded]
        if missing:
            raise UserError(f"{calibration}: no model {', '.join(missing)} in the calibration (has "
                            f"{', '.join(loaded) or 'none'})")
        loaded = {m: loaded[m] for m in models}
    if not loaded:
        raise UserError(f"{calibration}: the calibration holds no fitted model")
    return loaded, meta


def _test_scale(cap: Capture, src: str, meta: dict[str, Any], ball_radius_mm, mm_per_px):
    """``(ball radius mm, mm per pixel)`` of the test presses: given, else recorded; a UserError
    without a radius or with another scale than the calibration's."""
    radius = ball_radius_mm or meta.get("ball_radius_mm") or cap.meta.get("ball_radius_mm")
    if not radius or not radius > 0:
        raise UserError(f"{src}: no ball radius (give --ball-radius MM; neither the calibration nor the capture "
                        "records one)")
    mm = mm_per_px or cap.mm_per_px or meta.get("mm_per_px")
    cal_mm = meta.get("mm_per_px")
    if cal_mm and mm and abs(float(cal_mm) / float(mm) - 1) > 1e-6:
        raise UserError(f"{src}: mm_per_px {mm} differs from the calibration's {cal_mm}; a calibration holds for "
                        "the sensor (and image size) it was made with")
    return float(radius), mm


def _detected_truth(found, shrink_px: float, detected: int, labelled: bool) -> dict[str, Any]:
    """How the test presses' circles were found, the circles and the drift removed (a note when
    none was accepted)."""
    refined = found.refine.get("iterations", 0) and found.refine.get("model")
    out: dict[str, Any] = {
        "method": (f"edge detector + centre refinement voted by a {found.refine['model']} model cross-fitted on the "
                   f"test presses ({found.refine['iterations']} passes)" if refined else
                   "edge detector alone (no light model votes for the centres)") +
                  f", contact radius minus a {shrink_px:g} px margin",
        "circles": [c.to_dict() for c in found.circles],
        "drift": found.options.drift}
    if not detected:
        out["note"] = ("the detector accepted no test press: no detected truth; "
                       + ("the hand labels" if labelled else "only the ball fit") + " judge the "
                       "calibration (iristac label TEST_CAPTURE.h5 draws labels)")
    return out


def _label_truth(loaded: dict[str, Any], cap: Capture, found, radius: float, shrink_px: float,
                 src: str) -> dict[str, Any]:
    """Every model against the test capture's hand labels, and the detector's median offset from them."""
    circles = capture_label_circles(cap, radius / found.mm_per_px, src)
    lab_samples = collect_samples(found.frames, found.reference, circles, radius, found.mm_per_px,
                                  shrink_px=shrink_px, saturation=found.saturation, exclude=found.markers)
    exact = exact_normals(cap, lab_samples)
    if exact is not None:  # a virtual sensor's: the gel's own normals, not the sphere cap's, near the rim
        lab_samples.normals = exact
    offsets = np.array([c.center_xy for c in found.circles]) - np.asarray(cap.labels["center_xy"], float)
    acc = np.array([c.accepted for c in found.circles])
    return {"method": "hand labels labels/center_xy, labels/radius_px (contact radius clamped to "
                      "0.95 x ball)" + ("; the normals of truth/normals (exact)" if exact is not None else ""),
            "center_offset_px_median": np.median(offsets[acc], axis=0).tolist() if acc.any() else None,
            "models": evaluate_models(loaded, lab_samples)}


def exact_normals(cap: Capture, samples) -> np.ndarray | None:
    """The samples' normals ``(N, 3)`` with each contact sample's taken from the capture's exact
    ``truth/normals (K, H, W, 3)`` (a virtual sensor's), or None when the capture has none."""
    exact = (cap.truth or {}).get("normals")
    if exact is None or np.asarray(exact).shape != (len(cap.frames), *cap.shape, 3):
        return None
    out = np.array(samples.normals, np.float64)
    m = samples.contact & (samples.press >= 0)
    n = np.asarray(exact, np.float64)[samples.press[m], samples.rows[m], samples.cols[m]]
    out[m] = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return out


def _add_cv_gaps(det: dict[str, Any], meta: dict[str, Any], truth: dict[str, Any], cv_truth: str) -> None:
    """Each model's CV error from the calibration beside its test error, the gap, and a note when
    the gap exceeds :data:`CV_GAP_WARN_DEG` (in place)."""
    cv = {k: (v.get("cv") or {}).get("cv_mean_angular_error_deg")
          for k, v in (meta.get("validation") or {}).items() if isinstance(v, dict)}
    for name, stats in det.items():
        c = cv.get(name)
        # CV and test compared on the same kind of truth: a calibration fitted to hand labels
        # was cross-validated against labels, so its gap is to the test presses' labels.
        same = (truth.get("labels") or {}).get("models", {}).get(name, {}) if cv_truth == "labels" else stats
        test = same.get("mean_deg")
        gap = None if c is None or test is None else test - c
        stats["cv_mean_deg"] = c
        stats["cv_truth"] = cv_truth if c is not None else None
        stats["cv_gap_deg"] = gap
        stats["note"] = (f"test error {test:.2f} deg differs from the CV error {c:.2f} deg by more than "
                         f"{CV_GAP_WARN_DEG:g} deg ({cv_truth} truth): the CV figure does not describe new presses"
                         if gap is not None and abs(gap) > CV_GAP_WARN_DEG else None)


def _model_problems(report: dict[str, Any] | None, stats: dict[str, Any], ball: dict[str, Any]) -> list[str]:
    """Why a model's figures here are not results: its calibration's verdict
    (:func:`calibration.gate.model_problems`) and what the test presses show."""
    from calibration.gate import MAX_BALL_RADIUS_ERROR

    out = [f"calibration: {p}" for p in ((report or {}).get("problems") or [])]
    if stats.get("invalid_fraction") is not None and stats["invalid_fraction"] >= 1.0:
        out.append("no valid prediction on the test presses")
    rad = ball.get("radius_error_median")
    if rad is not None and rad > MAX_BALL_RADIUS_ERROR:
        out.append(f"the test presses reconstruct as spheres {rad:.0%} off the ball (> {MAX_BALL_RADIUS_ERROR:.0%})")
    elif rad is None and any(p.get("reason", "ok") != "ok" for p in ball.get("per_press", [])):
        out.append("no test press reconstructs as a round bump")
    return out


def _check_compatible(models: dict[str, Any], cap: Capture, src: str) -> None:
    """A calibration applies to frames of its own size, patterns and channels: say so plainly otherwise."""
    p, h, w, c = np.asarray(cap.reference).shape
    for name, m in models.items():
        ref = m.stored_reference() if hasattr(m, "stored_reference") else None
        field = getattr(m, "field", None)
        want = ref.shape if ref is not None else (None if field is None else
                                                   (field.shape[0], field.shape[2], field.shape[3], field.shape[1]))
        if want is not None and tuple(want) != (p, h, w, c):
            raise UserError(f"{src}: frames are {p} pattern(s) x {h}x{w} px x {c} channel(s), but the calibration's "
                            f"'{name}' model was made for {want[0]} x {want[1]}x{want[2]} px x {want[3]}; a "
                            "calibration holds for the sensor and image size it was made with")


def format_report(result: dict[str, Any]) -> str:
    """The human-readable table of :func:`evaluate_calibration`'s result."""
    def f(v, spec=".2f", unit=""):
        return "-" if v is None else f"{v:{spec}}{unit}"

    lab = (result["truth"].get("labels") or {}).get("models", {})
    cv_truth = next((m.get("cv_truth") for m in result["models"].values() if m.get("cv_truth")), None)
    drift = result["truth"]["detected"].get("drift")
    lines = [f"{result['accepted']} of {result['presses']} test presses accepted"
             + (f" (drift removed from each: {drift})" if drift else "")]
    if result["truth"]["detected"].get("note"):
        lines.append("  " + result["truth"]["detected"]["note"])
    if cv_truth == "labels":
        lines.append("  calibrated on hand labels: its CV was judged against labels, compare it with the labels column")
    lines += [
             f"  {'model':6s} {'test mean':>9s} {'median':>7s} {'p90':>6s} {'invalid':>7s} {'CV mean':>8s} "
             f"{'labels':>7s} {'ball radius':>11s} {'depth':>7s}"]
    for name, m in result["models"].items():
        b = result["ball_fit"].get(name, {})
        rad = None if b.get("radius_error_median") is None else 100 * b["radius_error_median"]
        dep = None if b.get("depth_error_median") is None else 100 * b["depth_error_median"]
        lines.append(f"  {name:6s} {f(m['mean_deg']):>9s} {f(m['median_deg']):>7s} {f(m['p90_deg']):>6s} "
                     f"{f(m['invalid_fraction'], '.1%'):>7s} {f(m.get('cv_mean_deg')):>8s} "
                     f"{f(lab.get(name, {}).get('mean_deg')):>7s} {f(rad, '.1f', ' %'):>11s} {f(dep, '.1f', ' %'):>7s}"
                     + ("" if m.get("usable", True) else "  UNUSABLE"))
    lines.append("  (degrees; test = against the test capture's own circles from the edge detector; labels = against "
                 "its hand labels; CV = the calibration's own, against the "
                 f"{'hand labels' if cv_truth == 'labels' else 'circles it was fitted to'}; ball radius/depth = median "
                 "relative error of a sphere fitted to each reconstructed press)")
    for name, m in result["models"].items():
        b = result["ball_fit"].get(name, {})
        if b.get("radius_error_spread") is not None:
            rng = b.get("radius_error_median_range")
            lines.append(f"  ball fit: {name}: {b['fitted']} of {len(b['per_press'])} presses fitted; their median "
                         f"radius {b['radius_mm_median']:.3g} mm, {100 * b['radius_error_signed_median']:+.1f} % off "
                         f"the ball; single presses scatter by {100 * b['radius_error_spread']:.1f} % (1.48 MAD)"
                         + ("" if rng is None else
                            f"; the median |error| {100 * b['radius_error_median']:.1f} % would be "
                            f"{100 * rng[0]:.1f}-{100 * rng[1]:.1f} % on another draw of as many presses "
                            "(bootstrap, 10-90 %)"))
    for name, m in result["models"].items():
        if m.get("problems"):
            lines.append(f"  UNUSABLE: {name}: {'; '.join(m['problems'])} (its figures above are not results)")
        if m.get("note"):
            lines.append(f"  note: {name}: {m['note']}")
    return "\n".join(lines)
