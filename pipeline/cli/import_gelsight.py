"""``iristac import gelsight-npz FILE --out capture.h5`` (calls :func:`calibration.importers.import_gelsight_npz`)."""

from pipeline.cli._common import add_json_flag, print_json


def register(group):
    p = group.add_parser("gelsight-npz", help="import GelSight-style ball presses (npz, BGR) as a capture",
                         description="Convert a GelSight-style ball-press .npz (BGR frames, background, hand labels) "
                                     "into capture.h5 (RGB, one pattern, background as reference, labels kept).")
    p.add_argument("file", help="the .npz file")
    p.add_argument("--out", required=True, help="capture.h5 to write")
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from calibration.importers import import_gelsight_npz

    res = import_gelsight_npz(args.file, args.out)
    if args.json:
        print_json(res)
    else:
        print(f"wrote {res['out']}: {res['presses']} presses of {res['shape'][0]}x{res['shape'][1]} px, "
              f"labels {'kept' if res['labels'] else 'absent'}")
    return 0
