"""``iristac bench calibration``: time and cross-validated error of every calibration model.

With ``--sensors``: every sensor on hand instead (:mod:`pipeline.bench._calibration_sensors`).
With ``--shipped``: the DIGIT calibration shipped with its profile, on the unit it was built from
and on an altered copy of it, another unit (:mod:`pipeline.bench._calibration_shipped`;
``--rebuild OUT.h5`` builds it again).
With ``--prior``: a new virtual unit calibrated from 5 presses and another unit's calibration,
against its own 20-press calibration (:mod:`pipeline.bench._calibration_prior`).

Three cases: the shared real GelSight frames (30 presses, one RGB pattern; skipped when
``../shared/data`` is absent) with the hand-label comparison; the same frames split, presses
0-19 calibrating and 20-29 testing (:mod:`pipeline.bench._calibration_split`: CV beside test
error, detected and label truth, the ball fit, and the levers behind the fixed-split targets); and a synthetic
point-lit ring capture (bare-LED near field, 8-bit, noise 1 DN) with the gain and direction
errors against the exact truth.

``rows`` (the common format of ``iristac bench all``): one per model and case (knob
``calibration model (real|synthetic)``, error = cross-validated mean angular error), the full
calibration time, centre refinement on/off, the MLP's training steps (error vs time), and per
model and lever of the split (error = test-press mean angular error, with ``cv_deg``,
``labels_deg`` and ``ball_radius_error`` beside it).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

__all__ = ["add_arguments", "run", "format_table"]


def _shared_data() -> Path | None:
    from pipeline.bench._calibration_sensors import shared_data_dir

    d = shared_data_dir()
    p = None if d is None else d / "gelsight_ball_presses.npz"
    return p if p is not None and p.is_file() else None


def add_arguments(parser) -> None:
    parser.add_argument("--npz", default=None, help="GelSight-style npz (default ../shared/data/...)")
    parser.add_argument("--sensors", action="store_true",
                        help="instead: every sensor on hand (shared GelSight, drifted GelSight, DIGIT, DIGIT without "
                             "its no-contact frame, randomised virtual sensors, the same again with a soft gel's look and with "
                             "markers the presses move) calibrated on some presses and judged "
                             "on the others (pipeline/bench/_calibration_sensors.py)")
    from pipeline.bench._calibration_shipped import add_shipped_arguments

    add_shipped_arguments(parser)
    parser.add_argument("--prior", action="store_true",
                        help="instead: new virtual units calibrated from 5 presses with another unit's calibration "
                             "(calibrate --prior) against their own 20-press calibrations, on unseen presses "
                             "(pipeline/bench/_calibration_prior.py); with --shipped: the altered DIGIT unit calibrated from 5 of its "
                             "presses with the shipped calibration as the prior, beside the shipped one as it is")


def _progress(flag: str):
    """A progress line printer for one of the long runs (stderr, so ``--json`` stays clean)."""
    import sys

    return lambda m: print(f"iristac bench calibration {flag}: {m}", file=sys.stderr, flush=True)


def _rows(res, seconds_total):
    s = res.summary()
    rows = []
    for name, m in s["models"].items():
        rows.append({"model": name, "cv_mean_deg": m["cv_mean_angular_error_deg"],
                     "cv_median_deg": m["cv_median_angular_error_deg"], "seconds": m["seconds"],
                     "skipped": m.get("skipped")})
    return s, rows


def _model_rows(case: str, s: dict) -> list[dict]:
    return [{"knob": f"calibration model ({case})", "setting": name, "error": m["cv_mean_angular_error_deg"],
             "error_unit": "deg", "seconds": m["seconds"]} for name, m in s["models"].items() if not m.get("skipped")]


def _mlp_sweep(cap, steps: list[int]) -> list[dict]:
    """CV error and time of the MLP alone, per number of training steps (real frames)."""
    from calibration.calibrate import calibrate

    rows = []
    for n in steps:
        res = calibrate(cap, 2.0, cap.mm_per_px, ["mlp"], model_options={"mlp": {"epochs": n}})
        m = res.summary()["models"]["mlp"]
        rows.append({"knob": "mlp training steps (real)", "setting": n, "error": m["cv_mean_angular_error_deg"],
                     "error_unit": "deg", "seconds": m["seconds"]})
    return rows


def run(args) -> dict:
    from calibration.calibrate import calibrate
    from calibration.importers import load_gelsight_npz
    from calibration.synthetic import synthetic_sphere_capture
    from pipeline.results.evaluate import angular_error_deg

    quick = bool(getattr(args, "quick", False))
    if getattr(args, "shipped", False) or getattr(args, "rebuild", None):
        from pipeline.bench._calibration_shipped import run_shipped

        return run_shipped(args, log=_progress("--shipped"))
    if getattr(args, "sensors", False):
        from pipeline.bench._calibration_sensors import run_sensors

        return run_sensors(quick, log=_progress("--sensors"))
    if getattr(args, "prior", False):
        from pipeline.bench._calibration_prior import run_prior

        return run_prior(quick, log=_progress("--prior"))
    out: dict = {"cases": [], "rows": []}
    npz = Path(args.npz) if getattr(args, "npz", None) else _shared_data()
    if npz is not None:
        cap = load_gelsight_npz(npz)
        t = time.perf_counter()
        res = calibrate(cap, 2.0, cap.mm_per_px, ("all", "conv", "conv-fast"))
        total = time.perf_counter() - t
        s, rows = _rows(res, total)
        out["cases"].append({"case": f"real {npz.name} ({s['presses']} presses, {cap.shape[0]}x{cap.shape[1]})",
                             "total_seconds": total, "accepted": s["accepted"], "presses": s["presses"],
                             "center_error_px_median": s.get("center_error_px_median"),
                             "radius_error_px_median": s.get("radius_error_px_median"),
                             "center_offset_px_median": s.get("center_offset_px_median"),
                             "models": rows})
        out["rows"] += _model_rows("real", s)
        out["rows"].append({"knob": "full calibration (real, 30 presses)", "setting": "all models",
                            "error": s["models"][res.best_model]["cv_mean_angular_error_deg"], "error_unit": "deg",
                            "seconds": total})
        out["rows"].append({"knob": "centre refinement (real)", "setting": "off (edge detector, default)",
                            "error": s["models"]["near"]["cv_mean_angular_error_deg"], "error_unit": "deg",
                            "seconds": 0.0})
        t = time.perf_counter()
        refined = calibrate(cap, 2.0, cap.mm_per_px, ["near"], refine_model="near")
        rs = refined.summary()
        # Against its own (refined) circles: lower, and not comparable (docs/calibration.md, "Which truth").
        out["rows"].append({"knob": "centre refinement (real)", "setting": "near votes, 2 passes (own truth)",
                            "error": rs["models"]["near"]["cv_mean_angular_error_deg"], "error_unit": "deg",
                            "seconds": refined.meta["refine"].get("seconds", 0.0)})
        out["cases"][-1]["refined"] = {"near_cv_mean_deg": rs["models"]["near"]["cv_mean_angular_error_deg"],
                                       "center_error_px_median": rs.get("center_error_px_median"),
                                       "center_offset_px_median": rs.get("center_offset_px_median"),
                                       "refine_seconds": refined.meta["refine"].get("seconds", 0.0),
                                       "seconds": time.perf_counter() - t}
        if not quick:
            out["rows"] += _mlp_sweep(cap, [100, 200, 400, 800])
        from pipeline.bench._calibration_split import run_split

        split_case, split_rows = run_split(cap, quick)
        out["split"] = split_case
        out["rows"] += split_rows
    k = 8 if quick else 30
    cap, tr = synthetic_sphere_capture((120, 160), k, mm_per_px=0.1, ball_radius_mm=2.0, num_leds=12,
                                       peak_dn=140, seed=11)
    t = time.perf_counter()
    res = calibrate(cap, 2.0, models="all", illumination=tr.V)
    total = time.perf_counter() - t
    s, rows = _rows(res, total)
    want = tr.gains * tr.exposure / np.pi
    gain_err = float(np.abs(res.models["traced"].gains / want - 1).max()) if "traced" in res.models else None
    far_dir = None
    if "far" in res.models:
        L = res.models["far"].lights[:, 0]
        true = tr.V[:, 60, 80]
        far_dir = float(angular_error_deg(L / np.linalg.norm(L, axis=1, keepdims=True),
                                          true / np.linalg.norm(true, axis=1, keepdims=True)).max())
    out["cases"].append({"case": f"synthetic point ring, 12 LEDs, near field ({k} presses, 120x160, 8-bit, 1 DN)",
                         "total_seconds": total, "accepted": s["accepted"], "presses": s["presses"],
                         "traced_gain_error_max": gain_err, "far_direction_error_max_deg": far_dir,
                         "models": rows})
    out["rows"] += _model_rows("synthetic", s)
    out["rows"].append({"knob": f"full calibration (synthetic, {k} presses)", "setting": "all models",
                        "error": s["models"][res.best_model]["cv_mean_angular_error_deg"], "error_unit": "deg",
                        "seconds": total})
    return out


def format_table(result: dict) -> str:
    if result.get("shipped"):
        from pipeline.bench._calibration_shipped import format_shipped

        return "\n".join(format_shipped(result))
    if "sensors" in result:
        from pipeline.bench._calibration_sensors import format_sensors

        return "\n".join(format_sensors(result))
    if "prior" in result:
        from pipeline.bench._calibration_prior import format_prior

        return "\n".join(format_prior(result))
    lines = []
    for c in result["cases"]:
        lines.append(c["case"])
        lines.append(f"  accepted {c['accepted']}/{c['presses']}   full calibration (detect + fit + CV, all models) "
                     f"{c['total_seconds']:.2f} s")
        if c.get("center_error_px_median") is not None:
            off = c.get("center_offset_px_median") or [float("nan")] * 2
            lines.append(f"  detected circles vs hand labels: centre median {c['center_error_px_median']:.2f} px (median offset "
                         f"circle - label {off[0]:+.2f}, {off[1]:+.2f} px), radius median "
                         f"{c['radius_error_px_median']:.2f} px")
        if c.get("refined"):
            u = c["refined"]
            off = u.get("center_offset_px_median") or [float("nan")] * 2
            lines.append(f"  centres refined by the near model (the old default): near CV mean {u['near_cv_mean_deg']:.2f} "
                         f"deg against those circles, centre median {u['center_error_px_median']:.2f} px from the "
                         f"labels (offset {off[0]:+.2f}, {off[1]:+.2f} px); refinement took {u['refine_seconds']:.2f} s")
        if c.get("traced_gain_error_max") is not None:
            lines.append(f"  traced gains: max relative error {100 * c['traced_gain_error_max']:.2f} %")
        if c.get("far_direction_error_max_deg") is not None:
            lines.append(f"  far-field directions vs centre-pixel truth (near-field scene): max "
                         f"{c['far_direction_error_max_deg']:.2f} deg")
        lines.append(f"  {'model':8s} {'CV mean deg':>12s} {'CV median deg':>14s} {'seconds':>8s}")
        for r in c["models"]:
            if r["skipped"]:
                lines.append(f"  {r['model']:8s} skipped: {r['skipped']}")
            else:
                lines.append(f"  {r['model']:8s} {r['cv_mean_deg']:12.2f} {r['cv_median_deg']:14.2f} {r['seconds']:8.2f}")
    if result.get("split"):
        from pipeline.bench._calibration_split import format_split

        lines += format_split(result["split"])
    if result.get("rows"):
        lines.append("rows (knob / setting / error / seconds)")
        for r in result["rows"]:
            err = "-" if r["error"] is None else f"{r['error']:.2f} {r['error_unit']}"
            lines.append(f"  {r['knob']:38s} {str(r['setting']):22s} {err:>10s} {r['seconds']:8.2f} s")
    return "\n".join(lines)
