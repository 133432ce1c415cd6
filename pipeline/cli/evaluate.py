"""``iristac eval normals PRED --gt GT [--mask M] [--json]`` (calls :func:`pipeline.results.evaluate.evaluate_normals`) and
``iristac eval calibration CAL.h5 TEST.h5 [--ball-radius MM] [--json]`` (calls
:func:`calibration.evaluate.evaluate_calibration`)."""

from __future__ import annotations

from pipeline.cli._common import add_calibration_drift_flag, add_json_flag, drift_options, make_group, print_json


def register(sub, name, help_text):
    _, group = make_group(sub, name, help_text)
    p = group.add_parser("normals", help="mean and median angular error of a normal map",
                         description="Mean and median angular error (degrees) of predicted normals against ground "
                                     "truth over a mask. PRED and GT: normals.h5 (ours), .npy (H, W, 3) or .mat "
                                     "(DiLiGenT Normal_gt).")
    p.add_argument("pred", metavar="PRED")
    p.add_argument("--gt", required=True, metavar="GT")
    p.add_argument("--mask", metavar="M", help=".png (non-zero inside) or .npy; default: the files' own masks")
    p.add_argument("--index", type=int, default=0, help="contact instance in a normals.h5 (default 0)")
    add_json_flag(p)
    p.set_defaults(func=_run)
    c = group.add_parser("calibration", help="every model of a calibration on presses it never saw",
                         description="Apply every model of CAL.h5 to the presses of TEST_CAPTURE.h5 (same sensor, "
                                     "other presses): angular error against the test capture's own detected circles "
                                     "(and its hand labels, if any, reported separately), and a sphere fitted to each "
                                     "reconstructed press against the ball radius (no circle truth needed).")
    c.add_argument("calibration", metavar="CAL.h5")
    c.add_argument("test_capture", metavar="TEST_CAPTURE.h5")
    c.add_argument("--ball-radius", type=float, default=None, metavar="MM",
                   help="ball radius in mm (default: the calibration's)")
    c.add_argument("--model", action="append", default=None, metavar="NAME",
                   help="evaluate only this model (repeatable; default all)")
    add_calibration_drift_flag(c, "illumination drift removed from each test press (default: the one the calibration "
                                  "removed)")
    add_json_flag(c)
    c.set_defaults(func=_run_calibration)


def _run(args) -> int:
    from pipeline.results.evaluate import evaluate_normals

    r = evaluate_normals(args.pred, args.gt, args.mask, index=args.index)
    if args.json:
        print_json(r)
    else:
        print(f"mean {r['mean_deg']:.3f} deg, median {r['median_deg']:.3f} deg over {r['pixels']} pixels")
    return 0


def _run_calibration(args) -> int:
    from calibration.evaluate import evaluate_calibration, format_report

    r = evaluate_calibration(args.calibration, args.test_capture, args.ball_radius, models=args.model,
                             detect_options=drift_options(args.drift))
    if args.json:
        print_json(r)
    else:
        print(format_report(r))
    return 0
