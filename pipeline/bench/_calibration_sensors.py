"""``iristac bench calibration --sensors``: the user's workflow on every sensor on hand.

Per sensor, calibrate on some presses and judge on the others:

- the shared **GelSight** frames (``../shared/data/gelsight_ball_presses.npz``): presses 0-19
  calibrate, 20-29 test (:mod:`calibration.split`); also with every press drifted (per press
  and channel: gain up to +-15 %, offset up to +-30 DN, seeded) against the untouched
  reference, the same split;
- the **DIGIT** folder (``../shared/data/digit_ball_presses``) through ``import images
  --profile digit`` (so calibrated with the profile's drift model, ``field``; its
  no-contact frame found automatically, and a reference built from the presses preferred when
  they match it better, :func:`calibration.reference.compare_with_built`): presses 0-19
  calibrate, 20-29 test; then with the found frame kept (``--reference``), and the same folder
  without its no-contact frame (``frame_30.jpg``): the reference built from the presses (the
  same capture as the first row when that one preferred the built reference: not run twice);
  and as the documented workflow has it, two folders (presses 0-19 and 20-29, each with the
  no-contact frame) imported one by one, calibrated on the first and evaluated on the second;
- **randomised virtual sensors** (:func:`sim.virtual_sensor.random_sensor`, every effect:
  the gel's rim smoothing, markers, vignetting, optical blur, drift, column stripes, read noise, JPEG; sizes 120 x 160 to 640 x 480,
  portrait and landscape) with exact truth: 20 presses calibrate, 10 test; and the same
  sensors again, once with a soft gel's look (``soft_shading``: weak, broad shading and a
  glossy highlight at the contact's rim) and once with markers the presses move
  (``marker_motion``; calibrated with the dots found in the reference, as ``--markers auto``).

Per sensor: presses accepted (calibration and test), the median centre and radius error of
the accepted circles against the truth where there is one (the hand labels of the GelSight
frames, a convention of their own, docs/calibration.md; the exact circles of the virtual
sensors), the best model by CV, its CV, its error on the test presses against their
detected circles (and against the exact truth, virtual sensors), its truth-free ball fit on
the test presses, whether the quality gate passed, and seconds. The drift-model table compares
the drift models of :mod:`pipeline.normals.drift` on the real sensors (best model's test error and
ball fit); the rotated table ``field`` against ``gain_offset`` on six splits of each real capture
(:func:`calibration.split.rotated_splits`), so that a lead is not one split's luck.
The table ends with the targets it is held to, met or not (:func:`sensor_targets`).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sim.virtual_sensor import CONTACT_LOOK_EFFECTS

__all__ = ["DIGIT_BALL_MM", "DIGIT_MM_PER_PX", "SENSOR_MODELS", "REAL_TARGETS", "VIRTUAL_TRUTH_DEG", "LOOK_ACCEPTED",
           "LOOK_CENTRE_PX", "LOOK_TRUTH_DEG", "format_sensors", "linked_folder", "run_sensors", "sensor_targets",
           "shared_data_dir"]

#: The DIGIT folder's ball and pixel pitch (its README).
DIGIT_BALL_MM = 3.0
DIGIT_MM_PER_PX = 0.0266


def shared_data_dir() -> Path | None:
    """``../shared/data`` beside the checkout (or one level further up), where the real sensor
    frames live; None when there is none."""
    repo = Path(__file__).resolve().parents[2]
    for base in (repo.parent, repo.parent.parent):
        if (base / "shared" / "data").is_dir():
            return base / "shared" / "data"
    return None


def _circle_errors(circles, center_xy, radius_px) -> dict[str, Any]:
    acc = np.array([c.accepted for c in circles])
    if center_xy is None or not acc.any():
        return {"centre_error_px": None, "radius_error": None}
    c = np.array([x.center_xy for x in circles])[acc]
    r = np.array([x.radius_px for x in circles])[acc]
    t = np.asarray(center_xy, float)[acc]
    tr = np.asarray(radius_px, float)[acc]
    return {"centre_error_px": float(np.median(np.hypot(*(c - t).T))),
            "radius_error": float(np.median(r / tr - 1.0))}


def _split_row(name: str, cap, ball_mm: float, models, truth=None, test_capture=None) -> dict[str, Any]:
    """Calibrate on the split's training presses, evaluate on its test presses
    (:func:`calibration.split.split_evaluation`); one row of the table. With ``test_capture``,
    calibrate on all of ``cap`` and evaluate on that capture instead
    (:func:`calibration.split.calibrate_and_evaluate`: two folders, two imports)."""
    from calibration.split import TEST_PRESSES, TRAIN_PRESSES, calibrate_and_evaluate, split_evaluation

    train, test = TRAIN_PRESSES, TEST_PRESSES
    t = time.perf_counter()
    if test_capture is None:
        sp = split_evaluation(cap, ball_mm, models)
        idx = np.arange(len(cap.frames))
        presses = [len(idx[train]), len(idx[test])]
    else:
        sp = calibrate_and_evaluate(cap, test_capture, ball_mm, models)
        presses = [len(cap.frames), len(test_capture.frames)]
    seconds = time.perf_counter() - t
    res, ev, cal_s = sp["calibration"], sp["evaluation"], sp["seconds"]
    best = res.best_model
    s = res.summary()
    ball = ev["ball_fit"].get(best, {}) if best else {}
    row = {"sensor": name, "shape": list(cap.shape), "presses": presses,
           "accepted": [s["accepted"], ev["accepted"]], "best_model": best,
           "cv_deg": None if best is None else s["models"][best]["cv_mean_angular_error_deg"],
           "test_deg": None if best is None else ev["models"][best]["mean_deg"],
           "ball_radius_error": ball.get("radius_error_median"),
           "ball_median_radius_error": ball.get("radius_error_signed_median"),
           "ball_spread": ball.get("radius_error_spread"),
           "gate": s.get("quality_gate", {}).get("passed"), "gate_cause": s.get("quality_gate", {}).get("cause"),
           "calibrate_seconds": cal_s, "seconds": seconds, "reference": s.get("reference"),
           "drift_residual_dn": (s.get("drift") or {}).get("residual_dn_median"),
           "ball_presses": None if best is None else
           [sum(p["radius_error"] is not None for p in ev["ball_fit"][best]["per_press"]),
            len(ev["ball_fit"][best]["per_press"])],
           "models": {m: {"cv_deg": s["models"][m].get("cv_mean_angular_error_deg"),
                          "test_deg": ev["models"][m]["mean_deg"],
                          "ball_radius_error": ev["ball_fit"][m]["radius_error_median"],
                          "usable": ev["models"][m]["usable"], "problems": ev["models"][m]["problems"]}
                      for m in ev["models"]}}
    if truth is not None:
        from calibration.detect import Circle

        cal_err = _circle_errors(res.circles, truth[0][train], truth[1][train])
        test_circles = [Circle(tuple(c["center_xy"]), c["radius_px"], c["contact_radius_px"], c["quality"],
                               c["accepted"], c["reason"]) for c in ev["truth"]["detected"]["circles"]]
        test_err = _circle_errors(test_circles, truth[0][test], truth[1][test])
        row["centre_error_px"] = [cal_err["centre_error_px"], test_err["centre_error_px"]]
        row["radius_error"] = [cal_err["radius_error"], test_err["radius_error"]]
    if best is not None and "labels" in ev["truth"]:
        row["test_deg_truth"] = ev["truth"]["labels"]["models"][best]["mean_deg"]
    return row


def linked_folder(folder: Path, source: Path, names) -> Path:
    """``folder`` holding links to the files ``names`` of ``source`` (a folder to import, no copies)."""
    folder.mkdir()
    for n in names:
        (folder / n).symlink_to((source / n).resolve())
    return folder


#: Effects of the contact's own look, benchmarked as twins of the plain virtual sensors: the same
#: sensor (every other draw the same) with one of them added.
LOOK_EFFECTS = CONTACT_LOOK_EFFECTS


def _virtual_rows(seeds, models, tmp: Path, done=None, look: str | None = None) -> list[dict[str, Any]]:
    """One row per virtual sensor seed (every effect but :data:`LOOK_EFFECTS`, or with ``look`` added);
    ``done(row)`` after each (progress). A sensor with markers is calibrated as ``import images
    --markers auto`` leaves it: the dots found in its reference (:func:`calibration.markers.detect_markers`)."""
    from calibration.markers import detect_markers
    from pipeline.base.capture import read_capture
    from sim.virtual_sensor import SENSOR_EFFECTS, random_sensor, write_sensor_capture

    base = [e for e in SENSOR_EFFECTS if e not in LOOK_EFFECTS]
    rows = []
    for seed in seeds:
        sensor = random_sensor(seed, num_presses=30, effects=base + ([look] if look else []))
        path = tmp / (f"virtual_{seed}.h5" if look is None else f"virtual_{seed}_{look}.h5")
        out = write_sensor_capture(path, sensor, labels=True)
        cap = read_capture(path)
        if look == "marker_motion":
            cap.markers = detect_markers(cap.reference)
        truth = (np.asarray(out.truth.center_xy, float), np.asarray(out.truth.radius_px, float))
        h, w = cap.shape
        what = f"{len(sensor.effects)} effects" if look is None else f"+ {look.replace('_', ' ')}"
        name = f"virtual seed {seed} ({h}x{w}, ball {sensor.ball_radius_px:.0f} px, {what})"
        row = _split_row(name, cap, float(cap.meta["ball_radius_mm"]), models, truth)
        row["effects"] = list(sensor.effects)
        row["seed"], row["look"] = int(seed), look
        row["touching_border"] = int(np.asarray(out.truth.touches_border).sum())
        rows.append(row)
        if done is not None:
            done(row)
    return rows


def _drift_split(cap, ball_mm: float, model: str, drift: str, train, test) -> dict[str, Any]:
    """``model`` calibrated on ``train`` and judged on ``test`` with ``drift`` removed from both."""
    from calibration.calibrate import find_circles
    from calibration.detect import DetectOptions
    from calibration.evaluate import TEST_TRUTH
    from calibration.split import split_evaluation

    opt = DetectOptions(drift=drift)
    tc = find_circles(cap.select(test), ball_mm, detect_options=opt, strict=False, **TEST_TRUTH)
    sp = split_evaluation(cap, ball_mm, [model], train=train, test=test, test_circles=tc, detect_options=opt)
    res, ev = sp["calibration"], sp["evaluation"]
    return {"accepted": [res.summary()["accepted"], ev["accepted"]],
            "cv_deg": res.reports[model]["cv"]["cv_mean_angular_error_deg"],
            "test_deg": ev["models"][model]["mean_deg"],
            "ball_radius_error": ev["ball_fit"][model]["radius_error_median"],
            "residual_dn": (res.summary().get("drift") or {}).get("residual_dn_median")}


def _drift_model_rows(cases, model: str) -> list[dict[str, Any]]:
    """Test error and ball fit of ``model`` on each real case with each drift model (the fixed split)."""
    from calibration.split import TEST_PRESSES, TRAIN_PRESSES
    from pipeline.normals.drift import DRIFT_MODELS

    rows = []
    for name, cap, ball_mm in cases:
        for drift in DRIFT_MODELS:
            t = time.perf_counter()
            row = _drift_split(cap, ball_mm, model, drift, TRAIN_PRESSES, TEST_PRESSES)
            rows.append({"sensor": name, "drift": drift, "model": model, **row, "seconds": time.perf_counter() - t})
    return rows


#: The drift models the rotated table compares: the default (constants per channel) and the
#: smooth field a sensor profile may name (the DIGIT's).
ROTATED_DRIFTS = ("field", "gain_offset")


def _drift_rotation_rows(cases, model: str) -> list[dict[str, Any]]:
    """Test error and ball fit of ``model`` per real case, drift model and split of
    :func:`calibration.split.rotated_splits`: whether a drift model's lead holds beyond one split."""
    from calibration.split import rotated_splits

    return [{"sensor": name, "split": split, "drift": drift, **_drift_split(cap, ball_mm, model, drift, train, test)}
            for name, cap, ball_mm in cases
            for split, (train, test) in rotated_splits(len(cap.frames)).items()
            for drift in ROTATED_DRIFTS]


#: The models every row calibrates: the per-pixel ones, the convolutional network and its live
#: variant on the frame shrunk by 2.
SENSOR_MODELS = ("all", "conv", "conv-fast")


def run_sensors(quick: bool = False, models=SENSOR_MODELS, log=None) -> dict[str, Any]:
    """Every sensor on hand through calibrate (train presses) and eval calibration (test presses).

    ``log(message)``, when given, hears one line per finished row and before each drift table
    (the whole run takes about a quarter of an hour on two cores).
    """
    from calibration.image_import import load_images
    from calibration.importers import load_gelsight_npz
    from pipeline.normals.drift import drifted_capture

    data = shared_data_dir()
    out: dict[str, Any] = {"sensors": [], "drift_models": [], "quick": bool(quick)}
    real = []
    say = log or (lambda message: None)
    start = time.perf_counter()

    def done(row: dict[str, Any]) -> None:
        say(f"{row['sensor']}: {row['seconds']:.0f} s ({time.perf_counter() - start:.0f} s so far)")

    def add(row: dict[str, Any]) -> None:
        out["sensors"].append(row)
        done(row)

    with tempfile.TemporaryDirectory(prefix="iristac-bench-sensors-") as tmp:
        tmp = Path(tmp)
        if data is not None and (data / "gelsight_ball_presses.npz").is_file():
            gs = load_gelsight_npz(data / "gelsight_ball_presses.npz")
            labels = (np.asarray(gs.labels["center_xy"], float), np.asarray(gs.labels["radius_px"], float))
            add({**_split_row("GelSight (shared, 120x160)", gs, 2.0, models, labels), "target": "GelSight"})
            drifted = drifted_capture(gs, seed=0)
            add(_split_row("GelSight drifted (+-15 % gain, +-30 DN per press)", drifted, 2.0, models, labels))
            real.append(("GelSight", gs, 2.0))
            real.append(("drifted", drifted, 2.0))
        digit = None if data is None else data / "digit_ball_presses"
        if digit is not None and digit.is_dir():
            # As a DIGIT user imports: with its profile, whose drift model the calibration removes.
            cap, rep = load_images(digit, mm_per_px=DIGIT_MM_PER_PX, ball_radius_mm=DIGIT_BALL_MM, profile="digit")
            found = rep["reference_found"]
            if rep["reference"] == "built":
                name = f"DIGIT (--profile digit; {found} found, built preferred)"
            else:
                name = f"DIGIT (--profile digit; reference {found} found)"
            digit_row = _split_row(name, cap, DIGIT_BALL_MM, models)
            digit_row["reference_comparison"] = rep["reference_comparison"]
            digit_row["target"] = "DIGIT"
            add(digit_row)
            real.append(("DIGIT", cap, DIGIT_BALL_MM))
            if rep["reference"] == "built" and found is not None:
                kept, _ = load_images(digit, mm_per_px=DIGIT_MM_PER_PX, ball_radius_mm=DIGIT_BALL_MM, reference=found,
                                      profile="digit")
                add(_split_row(f"DIGIT, no-contact frame kept (--reference {found})", kept, DIGIT_BALL_MM, models))
            folder = linked_folder(tmp / "digit_no_reference", digit, [f.name for f in digit.glob("*.jpg")
                                                                         if f.name != found])
            built, brep = load_images(folder, mm_per_px=DIGIT_MM_PER_PX, ball_radius_mm=DIGIT_BALL_MM, profile="digit")
            name = "DIGIT without its no-contact frame (reference built)"
            if np.array_equal(built.frames, cap.frames) and np.array_equal(built.reference, cap.reference):
                # The folder with the frame already calibrated on this very reference: the same row.
                row = {**digit_row, "sensor": name + ": the same capture as the first DIGIT row", "seconds": 0.0,
                       "target": None}  # judged once, on the first DIGIT row
            else:
                row = _split_row(name, built, DIGIT_BALL_MM, models)
            row["reference_built"] = brep.get("reference_built")
            add(row)
            # The documented workflow: two folders (presses 0-19, 20-29), each with the
            # no-contact frame, each imported on its own (so each builds its own reference).
            imported = [load_images(linked_folder(tmp / f"digit_{part}", digit,
                                                   [f"frame_{i}.jpg" for i in presses] + ([found] if found else [])),
                                    ball_radius_mm=DIGIT_BALL_MM, profile="digit")[0]
                        for part, presses in (("train", range(0, 20)), ("test", range(20, 30)))]
            add(_split_row("DIGIT two folders (0-19, 20-29; each with the frame)", imported[0], DIGIT_BALL_MM,
                           models, test_capture=imported[1]))
        seeds = range(2) if quick else range(4)
        out["sensors"] += _virtual_rows(seeds, models, tmp, done)
        for look in LOOK_EFFECTS:  # the same sensors, each with one effect of the contact's look added
            out["sensors"] += _virtual_rows(seeds, models, tmp, done, look=look)
        if not quick and real:
            say("drift models on the fixed split (mlp)")
            out["drift_models"] = _drift_model_rows([c for c in real if c[0] != "drifted"], "mlp")
            say(f"drift models on six splits (mlp; {len(real) * 2 * 6} calibrations, about half the run)")
            out["drift_rotations"] = _drift_rotation_rows(real, "mlp")
    return out


#: What ``bench calibration --sensors`` is held to. Real sensors (the rows tagged ``target``):
#: the best model's test error and ball radius error at most these. Plain virtual sensors: the
#: best model's exact-truth error at most :data:`VIRTUAL_TRUTH_DEG` on every seed. A contact look
#: (:data:`LOOK_EFFECTS`): at least :data:`LOOK_ACCEPTED` of the presses accepted over its seeds,
#: every row's median circle centre within :data:`LOOK_CENTRE_PX` px of the exact one, and its
#: exact-truth error within :data:`LOOK_TRUTH_DEG` of the same seed without the look.
REAL_TARGETS = {"GelSight": (3.5, 0.03), "DIGIT": (3.5, 0.03)}
VIRTUAL_TRUTH_DEG = 2.0
LOOK_ACCEPTED, LOOK_CENTRE_PX, LOOK_TRUTH_DEG = 0.9, 2.0, 1.0


def sensor_targets(rows: list[dict[str, Any]]) -> list[str]:
    """One line per target the rows can judge: ``target ...: met`` or ``NOT met``, with the figures."""
    def verdict(ok: bool) -> str:
        return "met" if ok else "NOT met"

    out = []
    for r in rows:
        bound = REAL_TARGETS.get(r.get("target"))
        if bound is not None and r.get("test_deg") is not None and r.get("ball_radius_error") is not None:
            ok = r["test_deg"] <= bound[0] and r["ball_radius_error"] <= bound[1]
            out.append(f"target {r['target']}: test <= {bound[0]} deg and ball <= {100 * bound[1]:.0f} %: {verdict(ok)} "
                       f"({r['test_deg']:.2f} deg, {100 * r['ball_radius_error']:.1f} %)")
    plain = {r["seed"]: r for r in rows if "seed" in r and r.get("look") is None}
    truth = {k: r.get("test_deg_truth") for k, r in plain.items()}
    if truth and all(v is not None for v in truth.values()):
        ok = all(v <= VIRTUAL_TRUTH_DEG for v in truth.values())
        out.append(f"target virtual sensors: truth <= {VIRTUAL_TRUTH_DEG} deg on every seed: {verdict(ok)} ("
                   + ", ".join(f"seed {k} {v:.2f}" for k, v in sorted(truth.items())) + ")")
    for look in LOOK_EFFECTS:
        with_look = [r for r in rows if r.get("look") == look]
        if not with_look:
            continue
        acc, pre = sum(sum(r["accepted"]) for r in with_look), sum(sum(r["presses"]) for r in with_look)
        base = sum(sum(plain[r["seed"]]["accepted"]) for r in with_look if r["seed"] in plain)
        out.append(f"target {look}: >= {100 * LOOK_ACCEPTED:.0f} % of presses accepted: {verdict(acc >= LOOK_ACCEPTED * pre)} "
                   f"({acc}/{pre}; without the look {base})")
        centres = [c for r in with_look for c in (r.get("centre_error_px") or []) if c is not None]
        if centres:
            out.append(f"target {look}: circle centres within {LOOK_CENTRE_PX:g} px: "
                       f"{verdict(max(centres) <= LOOK_CENTRE_PX)} (row medians {min(centres):.2f}-{max(centres):.2f} px)")
        gaps = {r["seed"]: r["test_deg_truth"] - plain[r["seed"]]["test_deg_truth"] for r in with_look
                if r["seed"] in plain and None not in (r.get("test_deg_truth"), plain[r["seed"]].get("test_deg_truth"))}
        if gaps:
            out.append(f"target {look}: truth within {LOOK_TRUTH_DEG:g} deg of the same seed without it: "
                       f"{verdict(all(g <= LOOK_TRUTH_DEG for g in gaps.values()))} ("
                       + ", ".join(f"seed {k} {g:+.2f}" for k, g in sorted(gaps.items())) + ")")
    return out


def _f(v, spec=".2f", unit=""):
    return "-" if v is None else f"{v:{spec}}{unit}"


def format_sensors(result: dict[str, Any]) -> list[str]:
    """The ``--sensors`` table."""
    lines = [("sensors: calibrate on presses 0-19, test on 20-29 (virtual: 20 of 30 random presses, 10 test); "
             "test = best model (by CV) against the test presses' detected circles, truth = against the exact "
             "circles and the gel's exact normals (virtual), ball = median |radius error| of a sphere fitted to each reconstructed test press, "
             "r med = the median fitted radius against the ball's (signed: the scale the presses share), "
             "scatter = how much single presses scatter about it (1.48 MAD); "
             "centre/radius = accepted circles against the hand labels (GelSight: a convention ~2 px off) or the "
             "exact circles (virtual), calibration presses / test presses")]
    lines.append(f"  {'sensor':58s} {'accepted':>9s} {'centre px':>11s} {'radius':>13s} {'best':>5s} {'CV':>6s} "
                 f"{'test':>6s} {'truth':>6s} {'ball':>7s} {'r med':>7s} {'scatter':>7s} {'gate':>5s} {'s':>6s}")
    for r in result["sensors"]:
        ce = r.get("centre_error_px") or [None, None]
        re = r.get("radius_error") or [None, None]
        acc = f"{r['accepted'][0]}/{r['presses'][0]},{r['accepted'][1]}/{r['presses'][1]}"
        lines.append(f"  {r['sensor'][:58]:58s} {acc:>9s} {_f(ce[0]):>5s},{_f(ce[1]):>5s} "
                     f"{_f(None if re[0] is None else 100 * re[0], '+.1f')},{_f(None if re[1] is None else 100 * re[1], '+.1f'):>6s}% "
                     f"{r['best_model'] or '-':>5s} {_f(r['cv_deg']):>6s} {_f(r['test_deg']):>6s} "
                     f"{_f(r.get('test_deg_truth')):>6s} {_f(None if r['ball_radius_error'] is None else 100 * r['ball_radius_error'], '.1f', ' %'):>7s} "
                     f"{_f(None if r.get('ball_median_radius_error') is None else 100 * r['ball_median_radius_error'], '+.1f', ' %'):>7s} "
                     f"{_f(None if r.get('ball_spread') is None else 100 * r['ball_spread'], '.1f', ' %'):>7s} "
                     f"{'pass' if r['gate'] else 'FAIL':>5s} {r['seconds']:6.1f}")
    lines.append("  every model (CV / test / ball radius; UNUSABLE: the model's own verdict, its figures are no results):")
    unusable = []
    for r in result["sensors"]:
        parts = [f"{m} {_f(v['cv_deg'], '.1f')}/{_f(v['test_deg'], '.1f')}/"
                 f"{_f(None if v['ball_radius_error'] is None else 100 * v['ball_radius_error'], '.1f', '%')}"
                 + ("" if v.get("usable", True) else " UNUSABLE")
                 for m, v in r["models"].items()]
        lines.append(f"    {r['sensor'][:40]:40s} " + "  ".join(parts))
        unusable += [f"    {r['sensor'][:40]}: {m}: {'; '.join(v['problems'])}"
                     for m, v in r["models"].items() if not v.get("usable", True)]
    if unusable:
        lines.append("  why unusable:")
        lines += unusable
    balls = [f"{r['sensor'][:24]} {r['ball_presses'][0]}/{r['ball_presses'][1]}" for r in result["sensors"]
             if r.get("ball_presses")]
    if balls:
        lines.append("  test presses with a round reconstructed cap (the ball column's median is over these): "
                     + ", ".join(balls))
    lines += ["  " + t for t in sensor_targets(result["sensors"])]
    if result.get("drift_models"):
        lines.append("  drift models (mlp; CV / test / ball radius / drift left after removal, RMS DN):")
        for r in result["drift_models"]:
            lines.append(f"    {r['sensor']:9s} {r['drift']:12s} accepted {r['accepted'][0]}/20,{r['accepted'][1]}/10  "
                         f"{_f(r['cv_deg'])} / {_f(r['test_deg'])} / "
                         f"{_f(None if r['ball_radius_error'] is None else 100 * r['ball_radius_error'], '.1f', ' %')} / "
                         f"{_f(r['residual_dn'])}  {r['seconds']:.1f} s")
    if result.get("drift_rotations"):
        lines += format_drift_rotations(result["drift_rotations"])
    return lines


def format_drift_rotations(rows: list[dict[str, Any]]) -> list[str]:
    """The drift models over the six splits: per sensor and model, test deg / ball % per split and the means."""
    from calibration.split import ROTATIONS

    def pct(v):
        return None if v is None else 100 * v

    lines = ["  drift models over six splits (mlp; test deg / ball radius % on the ten presses held out; "
             "splits: " + ", ".join(f"{chr(65 + i)} = test {n}" for i, n in enumerate(ROTATIONS)) + "):",
             f"    {'sensor':9s} {'drift':12s} " + " ".join(f"{chr(65 + i):>11s}" for i in range(len(ROTATIONS)))
             + f" {'mean':>11s} {'ball <= 5 %':>11s}"]
    for sensor in dict.fromkeys(r["sensor"] for r in rows):
        for drift in dict.fromkeys(r["drift"] for r in rows):
            mine = [r for r in rows if r["sensor"] == sensor and r["drift"] == drift]
            cells = [f"{_f(r['test_deg'])}/{_f(pct(r['ball_radius_error']), '.1f')}" for r in mine]
            tests = [r["test_deg"] for r in mine if r["test_deg"] is not None]
            balls = [r["ball_radius_error"] for r in mine if r["ball_radius_error"] is not None]
            mean = f"{_f(np.mean(tests) if tests else None)}/{_f(pct(np.mean(balls)) if balls else None, '.1f')}"
            lines.append(f"    {sensor:9s} {drift:12s} " + " ".join(f"{c:>11s}" for c in cells)
                         + f" {mean:>11s} {sum(b <= 0.05 for b in balls):>6d} of {len(mine)}")
    return lines
