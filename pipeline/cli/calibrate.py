"""``iristac calibrate CAPTURE --ball-radius MM --mm-per-px MM --model M --out FILE``.

Calls :func:`calibration.calibrate.calibrate` and :meth:`CalibrationResult.save`.
"""

from pipeline.cli._common import (
    add_calibration_drift_flag,
    add_json_flag,
    drift_options,
    print_json,
    profile_metavar,
)

MODEL_CHOICES = ["far", "near", "traced", "lut", "mlp", "conv", "conv-fast", "all"]


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text)
    p.add_argument("capture", help="sphere-indentation capture.h5")
    sensor = p.add_argument_group("sensor and ball")
    sensor.add_argument("--profile", default=None, metavar=profile_metavar(),
                        help="sensor profile (a built-in name or a .yaml): its ball radius, pixel pitch, drift model "
                             "and MLP ensemble size where --ball-radius / --mm-per-px / --drift / --mlp-members are "
                             "not given (a capture imported with --profile calibrates with that profile's settings "
                             "anyway)")
    sensor.add_argument("--ball-radius", type=float, default=None,
                        help="ball radius in mm (default: the capture's ball_radius_mm, from import images "
                             "--ball-radius)")
    sensor.add_argument("--mm-per-px", type=float, default=None, help="pixel pitch (default: the capture's)")
    presses = p.add_argument_group("presses and their circles")
    presses.add_argument("--circles", choices=["auto", "detected", "labels"], default="auto",
                         help="contact circles the models are fitted to: detected (the edge detector's), labels (the "
                              "capture's hand labels, from import images --labels; radius clamped below the ball's), "
                              "auto = detected (default)")
    presses.add_argument("--no-refine", action="store_true",
                         help="keep the edge detector's centres (no photometric centre refinement)")
    presses.add_argument("--refine-model", choices=["auto", "far", "near", "traced", "mlp"], default="auto",
                         help="light model whose normals vote for the detected centres (auto: traced with "
                              "--illumination, else none: the detector's centres; see docs/calibration.md)")
    presses.add_argument("--markers", default=None, metavar="auto|none|MASK.png",
                         help="printed gel markers: detect dark dots in the reference (auto), none, or a mask image "
                              "(default: the capture's own marker mask, if it has one)")
    add_calibration_drift_flag(presses, "illumination drift removed from each press, fitted outside its contact "
                               "(default: the --profile's, else gain_offset: a gain and an offset per channel; "
                               "field: both quadratic in the image position)")
    models = p.add_argument_group("models")
    models.add_argument("--model", choices=MODEL_CHOICES, default="all",
                        help="model(s) to fit (default all: the per-pixel models; conv, the convolutional network "
                             "that sees a pixel's neighbourhood, and conv-fast, the same on the frame shrunk by 2 "
                             "for live use, only when named)")
    models.add_argument("--folds", type=int, default=5, help="cross-validation press groups")
    models.add_argument("--mlp-members", type=int, default=None, metavar="N",
                        help="fit the MLP as an ensemble of N nets (mean prediction; their agreement is the "
                             "per-pixel confidence): steadier on new presses than one net, whose figures move with "
                             "its seed; costs about 1.6x the calibration time with 3, and N times the MLP's time per "
                             "frame in reconstruct and live (default: the sensor profile's calibration_mlp_members, "
                             "3 for the DIGIT, else 1; docs/calibration.md, step 3)")
    models.add_argument("--conv-members", type=int, default=None, metavar="N",
                        help="average N networks for --model conv or conv-fast (default 2 for conv, 1 for "
                             "conv-fast): 1 halves conv's fit time and its time per frame, for about 0.1 deg more "
                             "error on the virtual sensors' unseen presses (docs/calibration.md, \"The colour change "
                             "relative to the reference\")")
    models.add_argument("--illumination", default=None,
                        help="illumination.h5 (LED fields V from iristac sim trace) for the traced model")
    models.add_argument("--correct-led-geometry", action="store_true",
                        help="traced model: also fit small LED position and tilt corrections")
    models.add_argument("--prior", default=None, metavar="UNIT_A_CAL.h5",
                        help="adapt another unit's calibration of the same sensor model (its MLP) to this unit's "
                             "presses (3-5 are enough when the transfer is measured to work; the error is leave-one-"
                             "press-out over them; docs/calibration.md, 'A new unit from a few presses')")
    models.add_argument("--adapt-steps", type=int, nargs=2, default=None, metavar=("MAP", "FINETUNE"),
                        help="with --prior: steps fitting the input map, then steps fine-tuning every weight "
                             "(default 300 80)")
    outs = p.add_argument_group("what is written")
    outs.add_argument("--out", required=True, help="calibration.h5 to write")
    outs.add_argument("--overlay", default=None,
                      help="also write an overlay PNG: every press with its circle and why it was accepted or "
                           "rejected (written even when the calibration is refused)")
    outs.add_argument("--force", action="store_true",
                      help="write the calibration even when the quality gate refuses it (its verdict is kept in the "
                           "file)")
    add_json_flag(outs)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from calibration.calibrate import calibrate, read_illumination
    from pipeline.base.errors import UserError

    # The flags are checked before any file is read.
    if args.correct_led_geometry and not args.illumination:
        raise UserError("--correct-led-geometry needs --illumination ILL.h5 (the LED fields to correct)")
    if args.mlp_members is not None and args.mlp_members < 1:
        raise UserError(f"--mlp-members must be at least 1 (nets in the MLP ensemble), got {args.mlp_members}")
    if args.mlp_members is not None and args.model not in ("mlp", "all"):
        raise UserError(f"--mlp-members {args.mlp_members} sizes the MLP ensemble, but --model {args.model} fits "
                        "no MLP (use --model mlp or all)")
    from calibration.models.conv import CONV_MODELS

    if args.conv_members is not None and args.conv_members < 1:
        raise UserError(f"--conv-members must be at least 1 (networks averaged), got {args.conv_members}")
    if args.conv_members is not None and args.model not in CONV_MODELS:
        raise UserError(f"--conv-members {args.conv_members} sizes the network's ensemble, but --model {args.model} "
                        f"fits no network (use --model {' or '.join(CONV_MODELS)})")
    opts: dict = {}
    if args.conv_members is not None:
        opts[args.model] = {"members": args.conv_members}
    if args.correct_led_geometry:
        opts["traced"] = {"correct_geometry": True}
    if args.mlp_members is not None:
        opts["mlp"] = {"members": args.mlp_members}
    if args.adapt_steps is not None and not args.prior:
        raise UserError("--adapt-steps sets how another unit's calibration is adapted: it needs --prior UNIT_A_CAL.h5")
    if args.prior:
        from pipeline.cli.calibrate_prior import run_prior

        return run_prior(args, fit_and_write, _print_summary)
    ill = read_illumination(args.illumination) if args.illumination else None
    ball, mm, detect = args.ball_radius, args.mm_per_px, drift_options(args.drift)
    if args.profile:
        from calibration.calibrate import profile_detect_options, profile_model_options
        from pipeline.capture.sensor_profiles import capture_defaults

        ball, mm = capture_defaults(args.profile, args.capture, ball, mm)
        detect = detect or profile_detect_options(args.profile)
        opts = {**profile_model_options(args.profile), **opts}
    return fit_and_write(args, lambda: calibrate(args.capture, ball, mm, args.model, folds=args.folds, illumination=ill,
                                                 model_options=opts, detect_options=detect,
                                                 refine_iterations=0 if args.no_refine else 2,
                                                 refine_model=args.refine_model, markers=args.markers,
                                                 circles=args.circles),
                         lambda res, s, refused: _print_summary(args, s, refused))


def fit_and_write(args, fit, report) -> int:
    """``fit()`` (a :class:`calibration.calibrate.CalibrationResult`), then what every
    calibration gets: the overlay (``--overlay``, also of a refused one's circles), the gate's
    verdict, the file (only when passed, or ``--force``), the summary (``--json``, else
    ``report(result, summary, refused)``); a refusal raised after the report."""
    from calibration.gate import CalibrationRefused

    try:
        res = fit()
    except CalibrationRefused as exc:
        if args.overlay and exc.circles:
            _overlay(args, exc.circles)
        raise
    if args.overlay:
        _overlay(args, res.circles)
    refused = res.verdict is not None and not res.verdict.passed
    if not refused or args.force:
        res.save(args.out, force=args.force)
    s = res.summary()
    if args.json:
        print_json(s)
    else:
        report(res, s, refused)
    if refused and not args.force:
        raise CalibrationRefused(res.verdict.message(f"{args.capture}") + f" Nothing written to {args.out}.",
                                 res.verdict)
    return 0


def _overlay(args, circles) -> None:
    from calibration.overlay import write_overlay
    from pipeline.base.capture import read_capture

    write_overlay(args.overlay, read_capture(args.capture), circles)


def _after_gain(ball: dict) -> str:
    """What the ball-fit line says after the raw figure: the spheres after the applied gain, the
    gain measured but not applied (the networks), or why there is none."""
    if ball.get("applied", True) and ball.get("radius_error") is not None:
        return f", {ball['radius_error']:+.1%} after it"
    if ball.get("gain"):
        return f" (its gain {ball['gain']:.3f} measured, not applied to this model)"
    return f" ({ball['note']})"


def _ensemble_source(name: str, args) -> str:
    """Where a model's ensemble size came from, as the summary line says it."""
    if name == "mlp":  # without --mlp-members an MLP ensemble can only have come from the sensor profile
        return "" if args.mlp_members is not None else ": the sensor profile's calibration_mlp_members"
    return "" if args.conv_members is not None else f": {name}'s default, --conv-members sets it"


def _print_summary(args, s, refused: bool) -> None:
    wrote = ("REFUSED, not written (--force writes it)" if refused and not args.force else
             f"wrote {args.out}" + (" (refused by the quality gate; written because of --force)" if refused else ""))
    print(f"{s['accepted']} of {s['presses']} presses accepted; {wrote}")
    print(f"  circles: {s['circles_used']}")
    for name, m in s["models"].items():
        if m.get("skipped"):
            print(f"  {name:7s} skipped: {m['skipped']}")
        elif m["cv_mean_angular_error_deg"] is None:
            print(f"  {name:7s} {m['note']}  {m['seconds']:6.2f} s")
        else:
            members = (m.get("fit") or {}).get("members", 1)
            whose = _ensemble_source(name, args)
            print(f"  {name:7s} CV mean {m['cv_mean_angular_error_deg']:6.2f} deg  median "
                  f"{m['cv_median_angular_error_deg']:6.2f} deg  {m['seconds']:6.2f} s"
                  + (f"  (ensemble of {members} nets{whose})" if members > 1 else "")
                  + ("" if m.get("usable", True) else "  UNUSABLE: " + "; ".join(m["problems"])))
    if "center_error_px_median" in s:
        off = s["center_offset_px_median"]
        print(f"  detected circles vs hand labels: centre {s['center_error_px_median']:.2f} px (median offset "
              f"{off[0]:+.2f}, {off[1]:+.2f} px), radius {s['radius_error_px_median']:.2f} px (medians)")
    drift = s.get("drift") or {}
    if drift:
        print(f"  reference: {s.get('reference')}; drift ({drift['model']}) removed from every press: "
              f"{drift['before_dn_median']:.1f} -> {drift['residual_dn_median']:.1f} DN RMS away from the contacts "
              "(medians)")
    ball = s.get("ball_fit")
    if ball:
        print(f"  ball fit ({ball['model']}, {ball['presses']} held-out presses, no circle needed): sphere radius "
              f"{ball['raw_radius_error']:+.1%} off the ball before the tilt gain{_after_gain(ball)}")
    gate = s.get("quality_gate") or {}
    if gate and not gate["passed"]:
        print(f"  quality gate: {'; '.join(gate['problems'])}")
        print(f"  likely cause: {gate['cause']}")
    print("  " + s["cv_note"].replace("CAL.h5", str(args.out)))
