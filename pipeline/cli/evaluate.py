"""``iristac eval normals PRED --gt GT [--mask M] [--json]`` (calls :func:`pipeline.evaluate.evaluate_normals`)."""

from __future__ import annotations

from pipeline.cli._common import add_json_flag, make_group, print_json


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


def _run(args) -> int:
    from pipeline.evaluate import evaluate_normals

    r = evaluate_normals(args.pred, args.gt, args.mask, index=args.index)
    if args.json:
        print_json(r)
    else:
        print(f"mean {r['mean_deg']:.3f} deg, median {r['median_deg']:.3f} deg over {r['pixels']} pixels")
    return 0
