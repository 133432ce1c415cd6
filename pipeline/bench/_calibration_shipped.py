"""``iristac bench calibration --shipped``: the DIGIT calibration shipped with its profile, on
the unit it was built from and on another unit, with no presses of that one.

The shipped calibration (:mod:`pipeline.capture.shipped`) is the MLP (the profile's three nets,
its drift model ``field``) calibrated on presses 0-19 of the shared DIGIT frames
(``../shared/data/digit_ball_presses``, MIT licence, Taxim project) with the no-contact frame,
imported as a user does (``iristac import images --profile digit``). It is judged, through
``eval calibration``'s path (:func:`calibration.evaluate.evaluate_calibration`: the detector
finds each test press's contact, no labels), on

- **the unit itself**: presses 20-29 with the no-contact frame (never seen by it);
- **another unit**: the same ten presses as an altered unit records them
  (:func:`calibration.altered_unit.make_altered_unit` with :data:`ALTERATION`: another
  resolution, turned, framed by a border its profile crops, another colour gain), imported
  through the altered unit's own profile. No press of it reaches the calibration: only its
  own no-contact frame is used, as ``live`` and ``reconstruct`` use a session's: for its
  reference and to match its colours to the shipped unit's
  (:func:`pipeline.capture.shipped.colour_gain`; every test capture, the unit's own too, goes
  through it; ``--unmatched`` also judges the altered copies as recorded).

With ``--prior`` too: the altered unit calibrated from five of its own presses
(:data:`PRIOR_PRESSES`) with the shipped calibration as the prior (``calibrate --prior``,
:func:`calibration.prior.calibrate_with_prior`), and the shipped calibration as it is, both
judged on the altered unit's other five presses (:data:`PRIOR_TEST`).

``--rebuild OUT.h5`` calibrates again (about 2 minutes), measures, and writes the calibration
with both figures in its ``shipped`` attribute (what ``live`` and ``reconstruct`` print); without
it the file shipped is measured as it is, and the figures stored in it are printed beside the
ones measured now.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any, Callable

__all__ = ["ALTERATION", "TRAIN_PRESSES", "TEST_PRESSES", "PRIOR_PRESSES", "PRIOR_TEST", "add_shipped_arguments",
           "build_shipped_calibration", "measure_shipped", "measure_shipped_prior", "run_shipped", "format_shipped"]

#: The presses the shipped calibration is built from, and those it is judged on.
TRAIN_PRESSES = tuple(range(0, 20))
TEST_PRESSES = tuple(range(20, 30))
#: With ``--prior``: the other unit's presses that adapt the shipped calibration, and those both are judged on.
PRIOR_PRESSES = tuple(range(20, 25))
PRIOR_TEST = tuple(range(25, 30))
#: The DIGIT folder's no-contact frame (both folders get it, as the documented workflow does).
CLEAN_FRAME = "frame_30.jpg"
#: What makes the other unit (an instance of :class:`calibration.altered_unit.Alteration`, built on use).
ALTERATION = {"size": (360, 480), "rotate": 270, "border": (12, 8, 20, 4), "gain": (0.85, 1.1, 0.92)}
#: Where the shipped calibration's frames come from, and their licence.
ATTRIBUTION = "DIGIT frames of the Taxim project (vocdex/Taxim, Copyright (c) 2021 CMURoboTouch)"


def add_shipped_arguments(parser) -> None:
    parser.add_argument("--shipped", action="store_true",
                        help="instead: the DIGIT calibration shipped with its profile, on held-out presses of the unit "
                             "it was built from and on an altered copy of them (another unit; no presses of it)")
    parser.add_argument("--rebuild", metavar="OUT.h5", default=None,
                        help="with --shipped: calibrate it again from the DIGIT frames, measure, and write it with the "
                             "figures (pipeline/capture/sensors/digit.calibration.h5 is the one shipped)")
    parser.add_argument("--frames", metavar="DIR", default=None,
                        help="with --shipped: the DIGIT frames (default ../shared/data/digit_ball_presses)")
    parser.add_argument("--altered-seeds", metavar="SEED", type=int, nargs="*", default=[],
                        help="with --shipped: also altered copies drawn at random from these seeds (resolution 0.5-0.9 "
                             "x, any turn, border, gains 0.8-1.15; calibration.altered_unit.Alteration.from_seed)")
    parser.add_argument("--unmatched", action="store_true",
                        help="with --shipped: also judge each altered copy without matching its colours to the "
                             "shipped unit's (live and reconstruct match them from the no-contact frame)")


def _digit_frames(frames) -> Path:
    from pipeline.base.errors import UserError
    from pipeline.bench._calibration_sensors import shared_data_dir

    if frames is not None:
        return Path(frames)
    data = shared_data_dir()
    if data is None or not (data / "digit_ball_presses").is_dir():
        raise UserError("bench calibration --shipped: no DIGIT frames (../shared/data/digit_ball_presses); give --frames")
    return data / "digit_ball_presses"


def _folder(folder: Path, source: Path, presses) -> Path:
    """``folder`` with links to the presses and the no-contact frame of ``source``."""
    from pipeline.bench._calibration_sensors import linked_folder

    return linked_folder(folder, source, [f"frame_{i}.jpg" for i in presses] + [CLEAN_FRAME])


def _judge(calibration, folder, profile, match_colour: bool = True) -> dict[str, Any]:
    """The MLP's figures on one folder of test presses (imported with ``profile``), their colours
    matched to the calibration's from the no-contact frame as ``live`` and ``reconstruct`` match
    them (:func:`pipeline.capture.shipped.colour_gain`), or as recorded."""
    from calibration.evaluate import evaluate_calibration
    from calibration.image_import import load_images
    from pipeline.capture.shipped import colour_matched_capture

    t = time.perf_counter()
    cap, _ = load_images(folder, profile=profile)
    gain = None
    if match_colour:
        cap, gain = colour_matched_capture(cap, calibration)
    ev = evaluate_calibration(calibration, cap, models=["mlp"])
    m, ball = ev["models"]["mlp"], ev["ball_fit"]["mlp"]
    return {"presses": ev["presses"], "accepted": ev["accepted"], "mean_deg": m["mean_deg"],
            "median_deg": m["median_deg"], "ball_radius_error": ball["radius_error_median"],
            "ball_radius_signed": ball["radius_error_signed_median"], "ball_fitted": ball["fitted"],
            "seconds": time.perf_counter() - t, "colour_gain": None if gain is None else [float(g) for g in gain]}


def measure_shipped(calibration, frames, tmp, log: Callable[[str], None] = lambda m: None,
                    seeds=(), unmatched: bool = False) -> dict[str, Any]:
    """The calibration's figures on the held-out presses of ``frames`` (a DIGIT folder) and on an
    altered copy of them: ``original`` and ``altered`` (``presses``, ``accepted``, ``mean_deg``,
    ``median_deg``, ``ball_radius_error`` (median |error| of the fitted radius),
    ``ball_radius_signed``, ``seconds``; ``alteration`` for the copy); ``seeded``: one such per
    seed of ``seeds`` (:meth:`calibration.altered_unit.Alteration.from_seed`). Every test
    capture's colours are matched to the calibration's from its no-contact frame, as ``live`` and
    ``reconstruct`` do; with ``unmatched``, every altered copy is also judged as recorded
    (``<case> not colour-matched`` rows in ``seeded``)."""
    from calibration.altered_unit import Alteration, make_altered_unit
    from pipeline.capture.sensor_profiles import load_profile

    tmp = Path(tmp)
    test = _folder(tmp / "test", Path(frames), TEST_PRESSES)
    alts = [("altered", Alteration(**ALTERATION))]
    alts += [(f"seed {s}", Alteration.from_seed(s, load_profile("digit").resolution)) for s in seeds]
    out: dict[str, Any] = {"original": _judge(calibration, test, "digit"), "seeded": []}
    log(f"original: {out['original']['accepted']} of {out['original']['presses']} presses accepted, mlp "
        f"{out['original']['mean_deg']:.2f} deg ({out['original']['seconds']:.0f} s)")
    for i, (case, alt) in enumerate(alts):
        unit = make_altered_unit(test, tmp / f"altered_{i}", alteration=alt)
        row = {**_judge(calibration, unit.frames, unit.profile), "alteration": alt.describe(), "case": case}
        log(f"{case}: {row['accepted']} of {row['presses']} presses accepted, mlp {row['mean_deg']:.2f} deg "
            f"({row['seconds']:.0f} s)")
        if i == 0:
            out["altered"] = row
        else:
            out["seeded"].append(row)
        if unmatched:
            row = {**_judge(calibration, unit.frames, unit.profile, False), "alteration": alt.describe(),
                   "case": f"{case} not colour-matched"}
            log(f"{row['case']}: mlp {row['mean_deg']:.2f} deg")
            out["seeded"].append(row)
    return out


def measure_shipped_prior(calibration, frames, tmp, log: Callable[[str], None] = lambda m: None) -> dict[str, Any]:
    """``--shipped --prior``: the altered unit (:data:`ALTERATION`) calibrated from its presses
    :data:`PRIOR_PRESSES` with ``calibration`` as the prior, as a user runs ``calibrate NEW.h5
    --prior`` (its colours as recorded: the adaptation learns them), against ``calibration`` as
    it is (colours matched from the no-contact frame, as ``live`` does); both judged on the
    altered unit's presses :data:`PRIOR_TEST`. Returns ``as_is`` and ``adapted`` (as
    :func:`measure_shipped`'s rows; ``adapted`` also ``loo_deg``, ``transfer`` and
    ``calibrate_seconds``)."""
    from calibration.altered_unit import Alteration, make_altered_unit
    from calibration.image_import import load_images
    from calibration.prior import calibrate_with_prior

    tmp, alt = Path(tmp), Alteration(**ALTERATION)
    new = make_altered_unit(_folder(tmp / "prior_new", Path(frames), PRIOR_PRESSES), tmp / "prior_new_unit",
                            alteration=alt)
    test = make_altered_unit(_folder(tmp / "prior_test", Path(frames), PRIOR_TEST), tmp / "prior_test_unit",
                             alteration=alt)
    as_is = _judge(calibration, test.frames, test.profile)
    log(f"--prior: the shipped calibration as it is on presses {PRIOR_TEST[0]}-{PRIOR_TEST[-1]}: "
        f"{as_is['mean_deg']:.2f} deg")
    t = time.perf_counter()
    cap, _ = load_images(new.frames, profile=new.profile)
    res = calibrate_with_prior(cap, calibration)
    seconds = time.perf_counter() - t
    adapted = _judge(res.save(tmp / "prior_cal.h5"), test.frames, test.profile, match_colour=False)
    transfer = res.meta["prior"]["transfer"]
    log(f"--prior: adapted from {len(PRIOR_PRESSES)} presses in {seconds:.0f} s: {adapted['mean_deg']:.2f} deg")
    return {"as_is": as_is, "adapted": {**adapted, "calibrate_seconds": seconds, "loo_deg": transfer.get("loo_deg"),
                                        "transfer": transfer}}


def build_shipped_calibration(frames, out, log: Callable[[str], None] = lambda m: None) -> dict[str, Any]:
    """Calibrate the DIGIT's shipped calibration from ``frames`` (presses :data:`TRAIN_PRESSES`
    and the no-contact frame, imported with ``--profile digit``; the MLP alone, seed 0),
    measure it (:func:`measure_shipped`) and write it to ``out`` with the figures in its
    ``shipped`` attribute. Returns the measurement plus ``calibrate_seconds`` and ``out``."""
    from calibration.calibrate import calibrate
    from calibration.image_import import load_images
    from pipeline.base.store import Record, read_record, write_record
    from pipeline.capture.shipped import SHIPPED_ATTR

    frames = Path(frames)
    with tempfile.TemporaryDirectory(prefix="iristac-shipped-") as tmp:
        t = time.perf_counter()
        cap, _ = load_images(_folder(Path(tmp) / "train", frames, TRAIN_PRESSES), profile="digit")
        res = calibrate(cap, None, models=["mlp"], seed=0)
        seconds = time.perf_counter() - t
        log(f"calibrated on {len(TRAIN_PRESSES)} presses in {seconds:.0f} s")
        cal_path = res.save(Path(tmp) / "cal.h5")
        measured = measure_shipped(cal_path, frames, tmp, log)
        rec = read_record(cal_path)
    info = {"sensor": "DIGIT", "profile": "digit", "presses": len(TRAIN_PRESSES), "licence": "MIT",
            "attribution": ATTRIBUTION, "licence_file": "LICENSE-digit-calibration.txt",
            "built_by": "iristac bench calibration --shipped --rebuild OUT.h5",
            "train_frames": [f"frame_{i}.jpg" for i in TRAIN_PRESSES] + [CLEAN_FRAME],
            "test_frames": [f"frame_{i}.jpg" for i in TEST_PRESSES] + [CLEAN_FRAME],
            "colour_matching": "one gain per channel from the no-contact frames (pipeline.capture.shipped.colour_gain)",
            "original": measured["original"], "altered": {k: v for k, v in measured["altered"].items() if k != "case"}}
    write_record(Path(out), Record(schema="calibration", data=rec.data, meta={**rec.meta, SHIPPED_ATTR: info}))
    return {**measured, "calibrate_seconds": seconds, "out": str(out)}


def run_shipped(args, log: Callable[[str], None]) -> dict[str, Any]:
    """``--shipped`` (and ``--rebuild``): the result :func:`format_shipped` prints."""
    from pipeline.base.errors import UserError
    from pipeline.capture.shipped import shipped_calibration_path, shipped_info

    frames = _digit_frames(getattr(args, "frames", None))
    t = time.perf_counter()
    if getattr(args, "rebuild", None):
        res = build_shipped_calibration(frames, args.rebuild, log)
        path = Path(args.rebuild)
    else:
        path = shipped_calibration_path("digit")
        if path is None:
            raise UserError("no calibration ships with the digit profile: build it with --shipped --rebuild OUT.h5")
        with tempfile.TemporaryDirectory(prefix="iristac-shipped-") as tmp:
            res = measure_shipped(path, frames, tmp, log, seeds=getattr(args, "altered_seeds", None) or (),
                                  unmatched=bool(getattr(args, "unmatched", False)))
            if getattr(args, "prior", False):
                res["prior"] = measure_shipped_prior(path, frames, tmp, log)
    stored = shipped_info(path)
    size = path.stat().st_size
    return {"shipped": True, "calibration": str(path), "size_bytes": size, "stored": stored, **res,
            "seconds": time.perf_counter() - t,
            "rows": [{"knob": "shipped DIGIT calibration (mlp)", "setting": case, "error": res[case]["mean_deg"],
                      "error_unit": "deg", "seconds": res[case]["seconds"]} for case in ("original", "altered")]}


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def _deg(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def format_shipped(result: dict[str, Any]) -> list[str]:
    """The table of :func:`run_shipped`'s result."""
    stored = result["stored"]
    lines = [f"shipped DIGIT calibration {result['calibration']} ({result['size_bytes'] / 1e6:.2f} MB; built from "
             f"{stored['presses']} presses, {stored['licence']}, {stored['attribution']})"]
    if result.get("calibrate_seconds") is not None:
        lines.append(f"  rebuilt: calibrated in {result['calibrate_seconds']:.0f} s, written to {result['out']}")
    lines.append(f"  {'unit':46s} {'accepted':>8s} {'mean deg':>9s} {'median':>7s} {'ball radius':>11s} "
                 f"{'seconds':>8s} {'stored deg':>10s}")
    for case, text in (("original", "the unit it was built from (presses 20-29)"),
                       ("altered", "another unit: altered copy of them, no presses")):
        r, s = result[case], stored[case]
        lines.append(f"  {text:46s} {r['accepted']:>3d} / {r['presses']:<3d} {_deg(r['mean_deg']):>9s} "
                     f"{_deg(r['median_deg']):>7s} {_pct(r['ball_radius_error']):>11s} {r['seconds']:8.1f} "
                     f"{_deg(s['mean_deg']):>10s}")
    for r in result.get("seeded", []):
        lines.append(f"  {'another unit (' + r['case'] + ')':46s} {r['accepted']:>3d} / "
                     f"{r['presses']:<3d} {_deg(r['mean_deg']):>9s} {_deg(r['median_deg']):>7s} "
                     f"{_pct(r['ball_radius_error']):>11s} {r['seconds']:8.1f} {'-':>10s}")
    gain = result["altered"].get("colour_gain")
    lines.append(f"  altered copy: {result['altered']['alteration']}"
                 + ("" if gain is None else f"; colours matched by {' / '.join(f'{g:.3f}' for g in gain)} (RGB)"))
    for r in result.get("seeded", []):
        if r.get("colour_gain") is None:
            lines.append(f"  {r['case']}: {r['alteration']}; colours not matched")
        else:
            lines.append(f"  {r['case']}: {r['alteration']}; colours matched by "
                         f"{' / '.join(f'{g:.3f}' for g in r['colour_gain'])} (RGB)")
    lines += _format_prior(result.get("prior"))
    o, a = result["original"]["mean_deg"], result["altered"]["mean_deg"]
    if o is not None and a is not None:
        lines.append(f"  another unit vs the unit itself: {a - o:+.2f} deg (target: within 3 deg)")
    lines.append(f"  total {result['seconds']:.0f} s")
    return lines


def _format_prior(prior: dict[str, Any] | None) -> list[str]:
    """``--prior``'s rows of :func:`format_shipped` (none without it)."""
    if not prior:
        return []
    lines = [f"  --prior: the altered unit from {len(PRIOR_PRESSES)} of its presses ({PRIOR_PRESSES[0]}-{PRIOR_PRESSES[-1]}), "
             f"judged on its presses {PRIOR_TEST[0]}-{PRIOR_TEST[-1]}"]
    for key, text in (("as_is", "shipped, as it is (colours matched)"), ("adapted", "calibrate --prior shipped")):
        r = prior[key]
        lines.append(f"  {text:46s} {r['accepted']:>3d} / {r['presses']:<3d} {_deg(r['mean_deg']):>9s} "
                     f"{_deg(r['median_deg']):>7s} {_pct(r['ball_radius_error']):>11s} {r['seconds']:8.1f}")
    a = prior["adapted"]
    transfer = a.get("transfer") or {}
    lines.append(f"  calibrate --prior: {a['calibrate_seconds']:.0f} s; its own estimate (leave one press out) "
                 f"{_deg(a.get('loo_deg'))} deg; {transfer.get('reason', '')}")
    return lines
