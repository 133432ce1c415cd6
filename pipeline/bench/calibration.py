"""``iristac bench calibration``: time and cross-validated error of every calibration model.

Two cases: the shared real GelSight frames (30 presses, one RGB pattern; skipped when
``../shared/data`` is absent) with the hand-label comparison, and a synthetic point-lit ring
capture (bare-LED near field, 8-bit, noise 1 DN) with the gain and direction errors against
the exact truth.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

__all__ = ["add_arguments", "run", "format_table"]


def _shared_data() -> Path | None:
    repo = Path(__file__).resolve().parents[2]
    for base in (repo.parent, repo.parent.parent):
        p = base / "shared" / "data" / "gelsight_ball_presses.npz"
        if p.is_file():
            return p
    return None


def add_arguments(parser) -> None:
    parser.add_argument("--npz", default=None, help="GelSight-style npz (default ../shared/data/...)")


def _rows(res, seconds_total):
    s = res.summary()
    rows = []
    for name, m in s["models"].items():
        rows.append({"model": name, "cv_mean_deg": m["cv_mean_angular_error_deg"],
                     "cv_median_deg": m["cv_median_angular_error_deg"], "seconds": m["seconds"],
                     "skipped": m.get("skipped")})
    return s, rows


def run(args) -> dict:
    from calibration.calibrate import calibrate
    from calibration.importers import load_gelsight_npz
    from calibration.models.base import angular_error_deg
    from calibration.synthetic import synthetic_sphere_capture

    out: dict = {"cases": []}
    npz = Path(args.npz) if getattr(args, "npz", None) else _shared_data()
    if npz is not None:
        cap = load_gelsight_npz(npz)
        t = time.perf_counter()
        res = calibrate(cap, 2.0, cap.mm_per_px, "all")
        total = time.perf_counter() - t
        s, rows = _rows(res, total)
        out["cases"].append({"case": f"real {npz.name} ({s['presses']} presses, {cap.shape[0]}x{cap.shape[1]})",
                             "total_seconds": total, "accepted": s["accepted"], "presses": s["presses"],
                             "center_error_px_median": s.get("center_error_px_median"),
                             "radius_error_px_median": s.get("radius_error_px_median"), "models": rows})
    k = 8 if getattr(args, "quick", False) else 30
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
    return out


def format_table(result: dict) -> str:
    lines = []
    for c in result["cases"]:
        lines.append(c["case"])
        lines.append(f"  accepted {c['accepted']}/{c['presses']}   full calibration (detect + fit + CV, all models) "
                     f"{c['total_seconds']:.2f} s")
        if c.get("center_error_px_median") is not None:
            lines.append(f"  circles vs hand labels: centre median {c['center_error_px_median']:.2f} px, radius median "
                         f"{c['radius_error_px_median']:.2f} px")
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
    return "\n".join(lines)
