"""The train/test split of ``iristac bench calibration``: presses 0-19 calibrate, 20-29 judge.

Per model, calibrated on the detected circles (the default) and on the hand labels
(``--circles labels``): leave-presses-out CV on the training presses beside the error on the
test presses against both truths (the detector's circles and the labels) and the ball fit
(:func:`calibration.split.four_way`); the fixed-split targets as met or not, with the setting that
meets them (:func:`calibration.split.split_targets`). Then which truth: the same calibrations
judged against test circles refined by each light-model family (the audit behind
:data:`calibration.evaluate.TEST_TRUTH`). Then the levers, each a row of error against time;
each changes one thing from the defaults of its setting and is chosen by its CV on the
training presses; levers that change the circles a model is fitted to are compared by the CV
against one fixed truth (``fixed CV``, :func:`calibration.split.fixed_truth_cv`); test figures
are reported, never tuned on.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

#: (setting, knob, value, models, calibrate keyword arguments). One change from the setting's defaults per row.
LEVERS: list[tuple[str, str, str, list[str], dict[str, Any]]] = [
    ("detected", "mlp rim weight", "1 (uniform)", ["mlp"], {"model_options": {"mlp": {"rim_weight": 1.0}}}),
    ("detected", "mlp rim weight", "4 (default)", ["mlp"], {}),
    ("detected", "mlp rim weight", "8", ["mlp"], {"model_options": {"mlp": {"rim_weight": 8.0}}}),
    ("detected", "mlp training steps", "200", ["mlp"], {"model_options": {"mlp": {"epochs": 200}}}),
    ("detected", "mlp training steps", "800", ["mlp"], {"model_options": {"mlp": {"epochs": 800}}}),
    ("detected", "mlp width", "16", ["mlp"], {"model_options": {"mlp": {"hidden": 16}}}),
    ("detected", "mlp width", "64", ["mlp"], {"model_options": {"mlp": {"hidden": 64}}}),
    ("detected", "mlp layers", "2", ["mlp"], {"model_options": {"mlp": {"layers": 2}}}),
    ("detected", "mlp samples", "8000", ["mlp"], {"model_options": {"mlp": {"max_samples": 8000}}}),
    ("detected", "mlp position", "quadratic in x, y", ["mlp"], {"model_options": {"mlp": {"position_degree": 2}}}),
    ("detected", "mlp position", "none", ["mlp"], {"model_options": {"mlp": {"position": False}}}),
    ("detected", "mlp features", "change only", ["mlp"], {"model_options": {"mlp": {"features": "change"}}}),
    ("detected", "mlp features", "colour + x, y (gs_sdk)", ["mlp"], {"model_options": {"mlp": {"features": "colour"}}}),
    ("detected", "tilt gain + clip", "off (mlp)", ["mlp"], {"tilt_correction": False}),
    ("detected", "tilt gain + clip", "off (near)", ["near"], {"tilt_correction": False}),
    ("detected", "lut position correction", "linear in x, y", ["lut"], {"model_options": {"lut": {"position_degree": 1}}}),
    ("detected", "near-field degree", "1", ["near"], {"model_options": {"near": {"degree": 1}}}),
    ("detected", "near-field degree", "3", ["near"], {"model_options": {"near": {"degree": 3}}}),
    ("detected", "rim margin (shrink_px)", "0 px (mlp)", ["mlp"], {"shrink_px": 0.0}),
    ("detected", "rim margin (shrink_px)", "4 px (mlp)", ["mlp"], {"shrink_px": 4.0}),
    ("detected", "centre refinement", "near votes (old default)", ["mlp"], {"refine_model": "near"}),
    ("detected", "centre refinement", "far votes", ["mlp"], {"refine_model": "far"}),
    ("detected", "centre refinement", "mlp votes", ["mlp"], {"refine_model": "mlp"}),
    ("labels", "mlp rim weight", "1 (uniform)", ["mlp"], {"model_options": {"mlp": {"rim_weight": 1.0}}}),
    ("labels", "mlp rim weight", "8", ["mlp"], {"model_options": {"mlp": {"rim_weight": 8.0}}}),
    ("labels", "mlp training steps", "200", ["mlp"], {"model_options": {"mlp": {"epochs": 200}}}),
    ("labels", "mlp training steps", "800", ["mlp"], {"model_options": {"mlp": {"epochs": 800}}}),
    ("labels", "mlp layers", "2", ["mlp"], {"model_options": {"mlp": {"layers": 2}}}),
    ("labels", "mlp samples", "8000", ["mlp"], {"model_options": {"mlp": {"max_samples": 8000}}}),
    ("labels", "mlp position", "quadratic in x, y", ["mlp"], {"model_options": {"mlp": {"position_degree": 2}}}),
    ("labels", "mlp position", "none", ["mlp"], {"model_options": {"mlp": {"position": False}}}),
    ("labels", "tilt gain + clip", "off (mlp)", ["mlp"], {"tilt_correction": False}),
]

#: calibrate() arguments that change the circles a model is fitted to (its own CV's truth).
CIRCLE_KNOBS = {"refine_iterations", "refine_model", "shrink_px", "circles"}

#: Test truths of the audit: how the test presses' circles are found (find_circles arguments).
AUDIT_TRUTHS = [("detector alone (the test truth)", {"refine_iterations": 0}),
                ("refined by near (cross-fitted)", {"refine_model": "near"}),
                ("refined by far (cross-fitted)", {"refine_model": "far"}),
                ("refined by mlp (cross-fitted)", {"refine_model": "mlp"})]


def _row(setting: str, knob: str | None, value: str, r: dict[str, Any], fixed_cv: float | None) -> dict[str, Any]:
    name = (f"calibration model (split, on {setting} circles)" if knob is None else
            f"calibration lever (split, on {setting} circles): {knob}")
    return {"knob": name, "lever": knob is not None, "setting": f"{r['model']} {value}",
            "calibrated_on": setting, "error": r["test_mean_deg"], "error_unit": "deg", "seconds": r["seconds"],
            "cv_deg": r["cv_mean_deg"], "fixed_cv_deg": fixed_cv, "labels_deg": r["labels_mean_deg"],
            "ball_radius_error": r["ball_radius_error"]}


def _audit(cap, test_circles, calibrations: dict[str, Any]) -> dict[str, Any]:
    """Each calibration's models against test circles refined by each family, the labels, and the ball fit."""
    from calibration.calibrate import find_circles
    from calibration.evaluate import evaluate_calibration, evaluate_models
    from calibration.split import TEST_PRESSES

    test = cap.select(TEST_PRESSES)
    rows = []
    base = np.array([c.center_xy for c in test_circles.circles])
    for name, kwargs in AUDIT_TRUTHS:
        found = test_circles if not kwargs.get("refine_model") else find_circles(test, 2.0, **kwargs)
        off = np.median(np.array([c.center_xy for c in found.circles]) - base, axis=0).tolist()
        rows.append({"truth": name, "offset_px": off,
                     "models": {cal: {m: s["mean_deg"] for m, s in evaluate_models(res.models, found.samples).items()}
                                for cal, res in calibrations.items()}})
    evs = {cal: evaluate_calibration(res, test, 2.0, circles=test_circles) for cal, res in calibrations.items()}
    lab = np.asarray(test.labels["center_xy"], float)
    rows.append({"truth": "hand labels", "offset_px": np.median(lab - base, axis=0).tolist(),
                 "models": {cal: {m: s["mean_deg"] for m, s in ev["truth"]["labels"]["models"].items()}
                            for cal, ev in evs.items()}})
    rows.append({"truth": "ball radius error, %", "offset_px": None,
                 "models": {cal: {m: 100 * b["radius_error_median"] for m, b in ev["ball_fit"].items()}
                            for cal, ev in evs.items()}})
    return {"rows": rows}


def run_split(cap, quick: bool = False) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The split case and its rows (the truth audit and the levers only when not ``quick``)."""
    from calibration.calibrate import calibrate
    from calibration.split import TRAIN_PRESSES, fixed_truth_cv, four_way, split_evaluation, split_targets, test_truth

    test_circles = test_truth(cap, 2.0)
    t = time.perf_counter()
    four = four_way(cap, 2.0, ("all", "conv", "conv-fast"), test_circles=test_circles)
    runs = four["settings"]
    ev = runs["detected"]["evaluation"]
    case = {"case": "split: calibrate on presses 0-19, test on 20-29 (shared real frames)",
            "calibration_seconds": {k: v["seconds"] for k, v in runs.items()},
            "total_seconds": time.perf_counter() - t, "test_accepted": ev["accepted"], "test_presses": ev["presses"],
            "test_truth": ev["truth"]["detected"]["method"], "rows": four["rows"], "best_by_cv": four["best"],
            "targets": split_targets(four),
            "label_offset_px": (ev["truth"].get("labels") or {}).get("center_offset_px_median")}
    rows = [_row(s, None, "(defaults)", r[s], None) for r in four["rows"] for s in r if s != "model"]
    if not quick:
        old = calibrate(cap.select(TRAIN_PRESSES), 2.0, models="all", refine_model="near")
        case["audit"] = _audit(cap, test_circles, {"detected": runs["detected"]["calibration"],
                                                   "near-refined (old default)": old,
                                                   "labels": runs["labels"]["calibration"]})
        for setting, knob, value, models, kwargs in LEVERS:
            kw = {"circles": setting, **kwargs}
            fixed = fixed_truth_cv(cap, 2.0, models[0], judge=setting, **kw) if CIRCLE_KNOBS & set(kwargs) else None
            for r in split_evaluation(cap, 2.0, models, test_circles=test_circles, **kw)["rows"]:
                rows.append(_row(setting, knob, value, r, fixed))
        # The fixed-truth CV of the default, beside the levers that change the circles.
        case["fixed_cv_default"] = fixed_truth_cv(cap, 2.0, "mlp")
    case["levers"] = [r for r in rows if r["lever"]]
    return case, rows


def format_split(case: dict[str, Any]) -> list[str]:
    def f(v, spec=".2f"):
        return "-" if v is None else format(v, spec)

    def pct(v):
        return "-" if v is None else f"{100 * v:.1f} %"

    secs = case["calibration_seconds"]
    lines = [case["case"],
             f"  calibration (all models, 20 presses) {secs['detected']:.2f} s on detected circles, "
             f"{secs['labels']:.2f} s on hand labels; {case['test_accepted']}/{case['test_presses']} test presses "
             f"accepted; best by CV: {case['best_by_cv']['detected']} (detected), {case['best_by_cv']['labels']} (labels)",
             f"  test truth: detected = {case['test_truth']}; labels = the hand labels (contact radius at most 0.95 x ball)"]
    off = case.get("label_offset_px")
    if off is not None:
        lines.append(f"  test circles vs hand labels: median offset {off[0]:+.2f}, {off[1]:+.2f} px (the labels' convention)")
    lines.append("  CV = presses 0-19 against the circles calibrated on; test det / test lab = presses 20-29 against "
                 "the detector's circles / the hand labels")
    lines.append(f"  {'':6s} {'calibrated on detected circles (default)':^52s} | {'calibrated on hand labels (--circles labels)':^46s}")
    lines.append(f"  {'model':6s} {'CV':>6s} {'test det':>8s} {'test lab':>8s} {'ball r':>7s} {'depth':>7s} {'s':>6s} | "
                 f"{'CV':>6s} {'test lab':>8s} {'test det':>8s} {'ball r':>7s} {'depth':>7s} {'s':>6s}")
    for r in case["rows"]:
        d, lab = r.get("detected", {}), r.get("labels", {})
        lines.append(f"  {r['model']:6s} {f(d.get('cv_mean_deg')):>6s} {f(d.get('test_mean_deg')):>8s} "
                     f"{f(d.get('labels_mean_deg')):>8s} {pct(d.get('ball_radius_error')):>7s} "
                     f"{pct(d.get('ball_depth_error')):>7s} {f(d.get('seconds'), '.1f'):>6s} | "
                     f"{f(lab.get('cv_mean_deg')):>6s} {f(lab.get('labels_mean_deg')):>8s} "
                     f"{f(lab.get('test_mean_deg')):>8s} {pct(lab.get('ball_radius_error')):>7s} "
                     f"{pct(lab.get('ball_depth_error')):>7s} {f(lab.get('seconds'), '.1f'):>6s}")
    lines.append("  fixed-split targets (best model by CV of each setting, on the test presses):")
    for t in case["targets"]:
        if t["target"] == "cv_gap":
            gaps = ", ".join(f"{g['model']} ({g['setting']}) {g['gap_deg']:+.2f} deg{'' if g['reported'] else ' NOT noted'}"
                             for g in t["gaps"]) or "none"
            lines.append(f"    {'CV vs test within 2 deg or noted':32s} {'met' if t['met'] else 'NOT met':40s} gaps over "
                         f"2 deg: {gaps}")
            continue
        fmt = pct if t["target"] == "ball_radius" else (lambda v: f"{v:.2f} deg")
        per = "; ".join(f"{k}: {v['model']} {fmt(v['value'])}" for k, v in t["per_setting"].items())
        where = f"met (calibrated on {' and '.join(t['met_in'])})" if t["met"] else "NOT met"
        where = f"{where:40s}"
        dflt = t.get("default")
        dtxt = "" if dflt is None else f"; default (detected): {'met' if dflt['value'] <= t['bound'] else 'NOT met'}"
        lines.append(f"    {t['what']:32s} {where} {per}{dtxt}")
    for r in case["rows"]:
        for s in ("detected", "labels"):
            note = (r.get(s) or {}).get("note")
            if note:
                lines.append(f"  note: {r['model']} (calibrated on {s}): {note}")
    if case.get("audit"):
        cals = list(case["audit"]["rows"][0]["models"])
        models = list(case["audit"]["rows"][0]["models"][cals[0]])
        lines.append("  which truth: test error (deg) of each calibration's models against test circles found each way")
        lines.append(f"  {'test circles':32s} {'offset px':>13s} | " + " | ".join(
            f"{c[:26]:^{7 * len(models)}s}" for c in cals))
        lines.append(f"  {'':32s} {'':>13s} | " + " | ".join(" ".join(f"{m:>6s}" for m in models) for _ in cals))
        for a in case["audit"]["rows"]:
            o = a["offset_px"]
            otxt = "" if o is None else f"{o[0]:+6.2f},{o[1]:+6.2f}"
            lines.append(f"  {a['truth']:32s} {otxt:>13s} | " + " | ".join(
                " ".join(f"{f(a['models'][c][m]):>6s}" for m in models) for c in cals))
    if case.get("levers"):
        fixed = case.get("fixed_cv_default")
        lines.append(f"  levers (one change from the setting's defaults; fixed CV = against the detector's circles "
                     f"with a 2 px margin, uncorrected; default mlp: {f(fixed)})")
        lines.append(f"  {'lever':52s} {'CV':>6s} {'fixed CV':>8s} {'test det':>8s} {'test lab':>8s} {'ball r':>7s} "
                     f"{'seconds':>8s}")
        for r in case["levers"]:
            name = f"on {r['calibrated_on']}: {r['knob'].split(': ', 1)[1]}: {r['setting']}"
            lines.append(f"  {name:52s} {f(r['cv_deg']):>6s} {f(r['fixed_cv_deg']):>8s} {f(r['error']):>8s} "
                         f"{f(r['labels_deg']):>8s} {pct(r['ball_radius_error']):>7s} {f(r['seconds']):>8s}")
    return lines
