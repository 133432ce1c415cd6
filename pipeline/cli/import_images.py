"""``iristac import images SOURCE --out capture.h5`` (calls :func:`calibration.importers.import_images`)."""

import sys

from pipeline.cli._common import add_json_flag, print_json, profile_metavar


def register(group):
    p = group.add_parser("images", help="import a folder of images or a video of ball presses as a capture",
                         description="Import your own sensor's ball presses: a folder of JPEG/PNG/TIFF files (or a "
                                     "video), one no-contact reference and one frame per press, into capture.h5. "
                                     "Bit depth is kept (16-bit stays 16-bit); colour is stored RGB.")
    p.add_argument("source", help="folder of images, or a video file")
    p.add_argument("--out", required=True, help="capture.h5 to write")
    p.add_argument("--mm-per-px", type=float, default=None,
                   help="pixel pitch on the gel (mm per pixel); required unless --profile gives it")
    p.add_argument("--profile", default=None, metavar=profile_metavar(),
                   help="sensor profile (a built-in name or a .yaml): pixel pitch, ball radius, and the camera "
                        "stream's crop/rotation/size")
    p.add_argument("--reference", default=None, metavar="NAME",
                   help="the no-contact frame: file name or stem (with --pattern: a press id; video: a frame index), "
                        "or 'build' (no clean frame: build it from the presses, needs --ball-radius); default: the "
                        "frame closest to the median of all frames, built when no frame stands out or (with "
                        "--ball-radius and 10+ presses) when the presses match a built one clearly better")
    p.add_argument("--pattern", default=None, metavar="TEMPLATE",
                   help='file-name template for several lighting patterns per press, e.g. "press{press}_led{pattern}.png"')
    p.add_argument("--ball-radius", type=float, default=None, metavar="MM",
                   help="radius of the pressed ball in mm (stored; calibrate uses it when not given)")
    p.add_argument("--labels", default=None, metavar="CSV", help="hand labels: rows name,x,y,radius_px (pixels)")
    p.add_argument("--markers", default="none", metavar="auto|none|MASK.png",
                   help="printed gel markers: detect dark dots in the reference (auto), none (default), or a mask image")
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from calibration.importers import import_images

    res = import_images(args.source, args.out, reference=args.reference, pattern=args.pattern,
                        mm_per_px=args.mm_per_px, ball_radius_mm=args.ball_radius, labels=args.labels,
                        markers=args.markers, profile=args.profile,
                        log=lambda m: print(f"iristac import images: {m}", file=sys.stderr, flush=True))
    if args.json:
        print_json(res)
        return 0
    ref = f"reference {res['reference']!r}"
    if res.get("reference_built"):
        ref = f"reference {res['reference_built']['note']}"
    elif res["reference_auto"]:
        ref += (f" (found automatically: largest local difference to the median frame {res['reference_distance']:.1f}, "
                f"next closest frame {res['next_closest_distance']:.1f})")
    print(f"wrote {res['out']}: {res['presses']} presses x {res['patterns']} pattern(s) of {res['shape'][0]}x"
          f"{res['shape'][1]} px, {res['channels']} channel(s), {res['bit_depth']}-bit; {ref}; labels "
          f"{'kept' if res['labels'] else 'absent'}; {res['markers']} marker pixels")
    for name in res.get("matching_profiles") or []:
        print(f"  the images are the size of the {name!r} sensor profile's: if this is that sensor, import with "
              f"--profile {name} (its pixel pitch, ball and calibration settings: docs/calibration.md, Sensor profiles)")
    return 0
