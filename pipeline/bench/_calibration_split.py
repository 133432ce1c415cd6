"""The train/test split of ``iristac bench calibration``: presses 0-19 calibrate, 20-29 judge.

Per model: leave-presses-out CV on the training presses beside the error on the test presses
(detected truth and hand labels) and the ball fit. Then the levers of issue 13, each a row of
error against time; each lever changes one thing from the defaults, and is chosen by its CV on
the training presses (the ``cv`` column); its test figures are reported, never tuned on.
"""

from __future__ import annotations

import time
from typing import Any

#: (knob, setting, models, calibrate keyword arguments). One change from the defaults per row.
LEVERS: list[tuple[str, str, list[str], dict[str, Any]]] = [
    ("mlp training steps", "200", ["mlp"], {"model_options": {"mlp": {"epochs": 200}}}),
    ("mlp training steps", "400 (default)", ["mlp"], {}),
    ("mlp training steps", "800", ["mlp"], {"model_options": {"mlp": {"epochs": 800}}}),
    ("mlp width", "64", ["mlp"], {"model_options": {"mlp": {"hidden": 64}}}),
    ("mlp weight decay", "1e-2", ["mlp"], {"model_options": {"mlp": {"weight_decay": 1e-2}}}),
    ("mlp ensemble", "3 members", ["mlp"], {"model_options": {"mlp": {"members": 3}}}),
    ("mlp features", "change only", ["mlp"], {"model_options": {"mlp": {"features": "change"}}}),
    ("mlp features", "colour + x, y (gs_sdk)", ["mlp"], {"model_options": {"mlp": {"features": "colour"}}}),
    ("mlp features", "no position", ["mlp"], {"model_options": {"mlp": {"position": False}}}),
    ("tilt gain + clip", "off (mlp)", ["mlp"], {"tilt_correction": False}),
    ("tilt gain + clip", "off (near)", ["near"], {"tilt_correction": False}),
    ("lut position correction", "linear in x, y", ["lut"], {"model_options": {"lut": {"position_degree": 1}}}),
    ("lut position correction", "quadratic in x, y (Taxim)", ["lut"],
     {"model_options": {"lut": {"position_degree": 2}}}),
    ("near-field degree", "1", ["near"], {"model_options": {"near": {"degree": 1}}}),
    ("near-field degree", "3", ["near"], {"model_options": {"near": {"degree": 3}}}),
    ("rim margin (shrink_px)", "0 px (mlp)", ["mlp"], {"shrink_px": 0.0}),
    ("rim margin (shrink_px)", "4 px (mlp)", ["mlp"], {"shrink_px": 4.0}),
    ("centre refinement", "off (mlp)", ["mlp"], {"refine_iterations": 0}),
    ("centre refinement", "mlp votes (mlp)", ["mlp"], {"refine_model": "mlp"}),
]


#: calibrate() arguments that change how the circles (the truth) are found.
CIRCLE_KNOBS = {"refine_iterations", "refine_model", "shrink_px", "markers"}


def _row(knob: str, setting: str, r: dict[str, Any]) -> dict[str, Any]:
    return {"knob": f"calibration lever (split): {knob}", "setting": f"{r['model']} {setting}",
            "error": r["test_mean_deg"], "error_unit": "deg", "seconds": r["seconds"],
            "cv_deg": r["cv_mean_deg"], "labels_deg": r["labels_mean_deg"], "ball_radius_error": r["ball_radius_error"]}


def run_split(cap, quick: bool = False) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The split case and its rows (levers only when not ``quick``)."""
    from calibration.calibrate import find_circles
    from calibration.split import TEST_PRESSES, best_row, split_evaluation

    test_circles = find_circles(cap.select(TEST_PRESSES), 2.0)
    t = time.perf_counter()
    base = split_evaluation(cap, 2.0, "all", test_circles=test_circles)
    case = {"case": "split: calibrate on presses 0-19, test on 20-29 (shared real frames)",
            "calibration_seconds": base["seconds"], "total_seconds": time.perf_counter() - t,
            "test_accepted": base["evaluation"]["accepted"], "models": base["rows"],
            "best_by_cv": best_row(base["rows"]).get("model"),
            "label_offset_px": (base["evaluation"]["truth"].get("labels") or {}).get("center_offset_px_median")}
    rows = [_row("model", "(defaults)", r) for r in base["rows"]]
    if not quick:
        for knob, setting, models, kwargs in LEVERS:
            # A lever that changes how circles are found gets test circles found its way too.
            own = test_circles if not CIRCLE_KNOBS & set(kwargs) else None
            for r in split_evaluation(cap, 2.0, models, test_circles=own, **kwargs)["rows"]:
                rows.append(_row(knob, setting, r))
    case["levers"] = [r for r in rows if not r["knob"].endswith(": model")]
    return case, rows


def format_split(case: dict[str, Any]) -> list[str]:
    def f(v, spec=".2f"):
        return "-" if v is None else format(v, spec)

    lines = [case["case"], f"  calibration (all models, 20 presses) {case['calibration_seconds']:.2f} s; "
                           f"{case['test_accepted']}/10 test presses accepted; best by CV: {case['best_by_cv']}"]
    off = case.get("label_offset_px")
    if off is not None:
        lines.append(f"  test circles vs hand labels: median offset {off[0]:+.2f}, {off[1]:+.2f} px (the labels' bias)")
    lines.append(f"  {'model':6s} {'CV deg':>7s} {'test deg':>9s} {'labels deg':>10s} {'ball radius':>11s} "
                 f"{'ball depth':>10s} {'gain':>6s} {'seconds':>8s}")
    for r in case["models"]:
        rad = None if r["ball_radius_error"] is None else 100 * r["ball_radius_error"]
        dep = None if r["ball_depth_error"] is None else 100 * r["ball_depth_error"]
        lines.append(f"  {r['model']:6s} {f(r['cv_mean_deg']):>7s} {f(r['test_mean_deg']):>9s} "
                     f"{f(r['labels_mean_deg']):>10s} {f(rad, '.1f'):>9s} % {f(dep, '.1f'):>8s} % "
                     f"{f(r['tilt_gain'], '.3f'):>6s} {f(r['seconds']):>8s}")
    for r in case["models"]:
        if r.get("note"):
            lines.append(f"  note: {r['model']}: {r['note']}")
    if case.get("levers"):
        lines.append(f"  {'lever':58s} {'CV deg':>7s} {'test deg':>9s} {'labels':>7s} {'ball r':>7s} {'seconds':>8s}")
        for r in case["levers"]:
            rad = None if r["ball_radius_error"] is None else 100 * r["ball_radius_error"]
            name = f"{r['knob'].split(': ', 1)[1]}: {r['setting']}"
            lines.append(f"  {name:58s} {f(r['cv_deg']):>7s} {f(r['error']):>9s} {f(r['labels_deg']):>7s} "
                         f"{f(rad, '.1f'):>5s} % {f(r['seconds']):>8s}")
    return lines
