"""``iristac calibrate NEW.h5 --prior UNIT_A_CAL.h5 --out NEW_CAL.h5``: another unit's calibration
adapted to this unit's presses (:func:`calibration.prior.calibrate_with_prior`)."""

__all__ = ["run_prior", "IGNORED_WITH_PRIOR"]

#: calibrate's flags that choose what a prior already fixed (the model and its settings).
IGNORED_WITH_PRIOR = ("illumination", "correct_led_geometry", "mlp_members", "circles", "refine_model", "no_refine")


def run_prior(args, fit_and_write, print_summary) -> int:
    """Adapt, then gate, write and report as every calibration (``fit_and_write``:
    :func:`pipeline.cli.calibrate.fit_and_write`; ``print_summary``: its summary lines)."""
    from calibration.prior import calibrate_with_prior
    from pipeline.base.errors import UserError
    from pipeline.cli._common import drift_options

    if args.model not in ("mlp", "all"):
        raise UserError(f"--prior adapts the prior's MLP; --model {args.model} asks for another model (use --model mlp "
                        "or leave it out)")
    given = [f"--{n.replace('_', '-')}" for n in IGNORED_WITH_PRIOR
             if getattr(args, n, None) not in (None, False, "auto")]
    if given:
        raise UserError(f"{', '.join(given)}: not used with --prior (the prior fixes the model; the new presses' "
                        "circles are the detector's)")
    ball, mm = args.ball_radius, args.mm_per_px
    if args.profile:
        from pipeline.capture.sensor_profiles import capture_defaults

        ball, mm = capture_defaults(args.profile, args.capture, ball, mm)
    steps = {}
    if args.adapt_steps is not None:
        if min(args.adapt_steps) < 0:
            raise UserError(f"--adapt-steps needs two counts >= 0 (map, fine-tune), got {args.adapt_steps}")
        steps = {"steps": args.adapt_steps[0], "finetune_steps": args.adapt_steps[1]}

    def report(res, s, refused) -> None:
        import argparse

        # The MLP line names no sensor profile as the source of an ensemble: the prior's nets are the prior's.
        print_summary(argparse.Namespace(**{**vars(args), "mlp_members": len(res.models["mlp"].nets)}), s, refused)
        t = s["prior"]["transfer"]
        print(f"  prior: {args.prior} ({s['prior']['presses']} presses, MLP CV {_deg(s['prior']['cv_deg'])}); "
              f"adapted on {s['accepted']} presses; the MLP line's CV is leave-one-press-out over them")
        print(f"  transfer: {'measured' if t['transfers'] else 'NOT measured'}: {t['reason']}; the gate needs "
              f"{t['min_accepted']} accepted presses")

    return fit_and_write(args, lambda: calibrate_with_prior(args.capture, args.prior, ball, mm, markers=args.markers,
                                                            detect_options=drift_options(args.drift), **steps),
                         report)


def _deg(v) -> str:
    return "-" if v is None else f"{v:.2f} deg"
