"""``iristac import diligent DIR --out capture.h5`` (calls :func:`pipeline.capture.diligent.import_diligent`)."""

from __future__ import annotations

from pipeline.cli._common import add_json_flag, print_json


def register(group):
    text = "import a DiLiGenT-layout folder as a capture with far-field lights"
    p = group.add_parser("diligent", help=text, description=text)
    p.add_argument("folder", metavar="DIR", help="DiLiGenT object folder (filenames.txt, light_*.txt, mask.png, PNGs)")
    p.add_argument("--out", required=True, metavar="capture.h5")
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pipeline.capture.diligent import import_diligent

    r = import_diligent(args.folder, args.out)
    if args.json:
        print_json(r)
    else:
        gt = ", with ground-truth normals" if r["has_ground_truth"] else ""
        print(f"wrote {r['out']}: {r['images']} images {r['width']}x{r['height']}, {r['mask_pixels']} mask pixels{gt}")
    return 0
