"""``iristac bench calibration --prior``: a new unit from 5 presses and another unit's calibration.

Per design seed, three units of one virtual design (:func:`sim.virtual_sensor.random_sensor` at
120 x 160, every effect but markers, JPEG and the contact looks;
:func:`sim.virtual_sensor.sibling_unit` draws each unit's LEDs, camera pose, gel brightness,
drift and presses): unit A, 20 presses, calibrated (MLP) as the prior; unit B, 30 presses:
presses 20-29 are the unseen test presses, and B is calibrated four ways, each judged on them
(:func:`calibration.evaluate.evaluate_calibration`, the detected circles as truth):

- its own 20-press calibration (presses 0-19): the reference figure;
- the prior adapted from presses 0-4 (:func:`calibration.prior.calibrate_with_prior`), with its
  leave-one-press-out estimate beside it;
- the prior as it is (no adaptation);
- its own calibration of presses 0-4 only.

The target: the adapted prior within 1 deg of the own 20-press calibration on the test presses.

With the shared GelSight frames on hand (``../shared/data/gelsight_ball_presses.npz``), one real
check beside it (:func:`gelsight_row`): the MLP of presses 0-19 is the prior; presses 20-29 with
every frame's colours mixed by :data:`OTHER_LEDS` (another unit's LEDs: other gains, some
crosstalk, 4 DN more light) are the new unit; it is adapted from 20-24 and judged on 25-29,
against the prior's figure on the unaltered 25-29. The gel and the camera pose are the same
unit's: only the LEDs differ.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["run_prior", "format_prior", "gelsight_row", "prior_row", "PRIOR_SEEDS", "FEW_PRESSES", "TARGET_GAP_DEG",
           "OTHER_LEDS"]

#: Design seeds of the full run (``--quick``: the first).
PRIOR_SEEDS = (0, 1, 2, 3, 4)
#: Presses of the new unit the prior is adapted from.
FEW_PRESSES = 5
#: The adapted prior's test error may exceed the unit's own 20-press calibration's by this (deg).
TARGET_GAP_DEG = 1.0


def _units(seed: int):
    from sim.virtual_sensor import SENSOR_EFFECTS, random_sensor, render_sensor, sibling_unit

    effects = [e for e in SENSOR_EFFECTS if e not in ("markers", "marker_motion", "soft_shading", "jpeg")]
    design = random_sensor(seed, shape=(120, 160), num_presses=1, effects=effects)
    a = render_sensor(sibling_unit(design, 1000 + seed, num_presses=20)).capture
    b = render_sensor(sibling_unit(design, 2000 + seed, num_presses=30)).capture
    return design, a, b


def _test_deg(calibration, test) -> float | None:
    from calibration.evaluate import evaluate_calibration

    return evaluate_calibration(calibration, test, models=["mlp"])["models"]["mlp"]["mean_deg"]


def prior_row(seed: int, tmp: Path) -> dict[str, Any]:
    """One design seed: the four calibrations of unit B and their test errors (see the module docstring)."""
    from calibration.calibrate import calibrate
    from calibration.prior import calibrate_with_prior

    t0 = time.perf_counter()
    design, a, b = _units(seed)
    prior_path = tmp / f"unit_a_{seed}.h5"
    ra = calibrate(a, None, models="mlp")
    ra.save(prior_path, force=True)
    test, few = b.select(slice(20, 30)), b.select(slice(0, FEW_PRESSES))
    t = time.perf_counter()
    own = calibrate(b.select(slice(0, 20)), None, models="mlp")
    own_s = time.perf_counter() - t
    t = time.perf_counter()
    adapted = calibrate_with_prior(few, prior_path)
    adapt_s = time.perf_counter() - t
    own_few = calibrate(few, None, models="mlp", folds=FEW_PRESSES)
    row = {"seed": seed, "shape": list(design.shape), "ball_px": design.ball_radius_px,
           "prior_cv_deg": ra.reports["mlp"]["cv"]["cv_mean_angular_error_deg"],
           "own20_cv_deg": own.reports["mlp"]["cv"]["cv_mean_angular_error_deg"], "own20_test_deg": _test_deg(own, test),
           "own20_seconds": own_s,
           "prior5_loo_deg": adapted.reports["mlp"]["cv"]["cv_mean_angular_error_deg"],
           "prior5_test_deg": _test_deg(adapted, test), "prior5_seconds": adapt_s,
           "prior5_gate": adapted.verdict.passed if adapted.verdict is not None else None,
           "prior5_transfers": adapted.meta["prior"]["transfer"]["transfers"],
           "prior_as_is_test_deg": _test_deg(prior_path, test),
           "own5_cv_deg": own_few.reports["mlp"]["cv"]["cv_mean_angular_error_deg"],
           "own5_test_deg": _test_deg(own_few, test)}
    ok = row["prior5_test_deg"] is not None and row["own20_test_deg"] is not None
    row["gap_deg"] = row["prior5_test_deg"] - row["own20_test_deg"] if ok else None
    row["met"] = bool(ok and row["gap_deg"] <= TARGET_GAP_DEG)
    row["seconds"] = time.perf_counter() - t0
    return row


def run_prior(quick: bool = False, seeds=None, log=None) -> dict[str, Any]:
    """Every design seed's row (:func:`prior_row`), the target's verdict and the common ``rows``."""
    seeds = list(seeds if seeds is not None else PRIOR_SEEDS[:1] if quick else PRIOR_SEEDS)
    out: dict[str, Any] = {"prior": [], "rows": []}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        for s in seeds:
            row = prior_row(s, Path(d))
            out["prior"].append(row)
            if log is not None:
                log(f"seed {s}: own 20 {row['own20_test_deg']:.2f}, prior + {FEW_PRESSES} {row['prior5_test_deg']:.2f} deg")
            out["rows"] += [
                {"knob": "new unit (virtual)", "setting": f"seed {s}: own 20 presses", "error": row["own20_test_deg"],
                 "error_unit": "deg", "seconds": row["own20_seconds"]},
                {"knob": "new unit (virtual)", "setting": f"seed {s}: prior + {FEW_PRESSES} presses",
                 "error": row["prior5_test_deg"], "error_unit": "deg", "seconds": row["prior5_seconds"]}]
    out["target"] = {"what": f"prior + {FEW_PRESSES} presses within {TARGET_GAP_DEG:g} deg of the unit's own 20-press "
                             "calibration on its unseen presses", "met": all(r["met"] for r in out["prior"])}
    from pipeline.bench._calibration_sensors import shared_data_dir

    data = shared_data_dir()
    if data is not None and (data / "gelsight_ball_presses.npz").is_file():
        out["real"] = gelsight_row(data / "gelsight_ball_presses.npz")
    out["seconds"] = time.perf_counter() - t0
    return out


#: The real check's other LEDs: ``rgb_out = OTHER_LEDS @ rgb_in + 4`` DN, every frame and the reference.
OTHER_LEDS = ((0.85, 0.06, 0.02), (0.04, 1.15, 0.05), (0.03, 0.02, 0.95))


def gelsight_row(npz) -> dict[str, Any]:
    """The real check on the shared GelSight frames (see the module docstring)."""
    import numpy as np

    from calibration.calibrate import calibrate
    from calibration.importers import load_gelsight_npz
    from calibration.prior import calibrate_with_prior

    t0 = time.perf_counter()
    cap = load_gelsight_npz(npz)
    mix = np.asarray(OTHER_LEDS)

    def other_leds(images):
        return np.clip(np.asarray(images, np.float64) @ mix.T + 4.0, 0, 255).astype(np.uint8)

    new = cap.select(slice(20, 30))
    new.frames, new.reference = other_leds(new.frames), other_leds(new.reference)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "prior.h5"
        prior = calibrate(cap.select(slice(0, 20)), 2.0, cap.mm_per_px, "mlp")
        prior.save(path, force=True)
        adapted = calibrate_with_prior(new.select(slice(0, FEW_PRESSES)), path, 2.0)
        test = slice(FEW_PRESSES, 10)
        row = {"case": "shared GelSight, presses 20-29 with other LEDs", "prior_cv_deg":
               prior.reports["mlp"]["cv"]["cv_mean_angular_error_deg"],
               "prior_original_test_deg": _test_deg(path, cap.select(slice(20 + FEW_PRESSES, 30))),
               "prior_as_is_test_deg": _test_deg(path, new.select(test)),
               "prior5_test_deg": _test_deg(adapted, new.select(test)),
               "prior5_loo_deg": adapted.reports["mlp"]["cv"]["cv_mean_angular_error_deg"],
               "prior5_gate": adapted.verdict.passed if adapted.verdict is not None else None}
    row["seconds"] = time.perf_counter() - t0
    return row


def _f(v, spec=".2f"):
    return "-" if v is None else format(v, spec)


def format_prior(result: dict[str, Any]) -> list[str]:
    """The table: one line per design seed."""
    lines = [f"A new virtual unit from {FEW_PRESSES} presses and another unit's calibration (MLP; test = mean "
             "angular error on 10 unseen presses, deg)",
             f"{'seed':>4} {'size':>8} {'prior CV':>8} {'own 20':>7} {'prior+5':>7} {'gap':>6} {'LOO est':>7} "
             f"{'as is':>6} {'own 5':>6} {'gate':>5} {'adapt s':>7} {'own20 s':>7}"]
    for r in result["prior"]:
        lines.append(f"{r['seed']:>4} {r['shape'][0]:>3}x{r['shape'][1]:<4} {_f(r['prior_cv_deg']):>8} "
                     f"{_f(r['own20_test_deg']):>7} {_f(r['prior5_test_deg']):>7} {_f(r['gap_deg'], '+.2f'):>6} "
                     f"{_f(r['prior5_loo_deg']):>7} {_f(r['prior_as_is_test_deg']):>6} {_f(r['own5_test_deg']):>6} "
                     f"{'pass' if r['prior5_gate'] else 'fail':>5} {r['prior5_seconds']:7.1f} "
                     f"{r['own20_seconds']:7.1f}")
    t = result["target"]
    lines.append(f"target: {t['what']}: {'met' if t['met'] else 'NOT met'}")
    r = result.get("real")
    if r:
        lines.append(f"real: {r['case']}: the prior (CV {_f(r['prior_cv_deg'])}) on the unaltered presses 25-29 "
                     f"{_f(r['prior_original_test_deg'])}; with the other LEDs as is {_f(r['prior_as_is_test_deg'])}, "
                     f"adapted from presses 20-24 {_f(r['prior5_test_deg'])} (LOO est {_f(r['prior5_loo_deg'])}, gate "
                     f"{'pass' if r['prior5_gate'] else 'fail'}; {r['seconds']:.0f} s)")
    if "seconds" in result:
        lines.append(f"time: {result['seconds']:.0f} s in all (per seed: rendering, the prior, the four calibrations "
                     "and their evaluations: " + ", ".join(f"{r['seconds']:.0f}" for r in result["prior"]) + " s)")
    lines.append("  (LOO est = the adapted calibration's own leave-one-press-out estimate over its 5 presses; as is = the "
                 "prior unchanged; own 5 = the unit calibrated from its 5 presses alone)")
    return lines
