"""``iristac sim sensor``: a randomised virtual tactile sensor's ball presses (calls
:func:`sim.virtual_sensor.random_sensor` and :func:`sim.virtual_sensor.write_sensor_capture` /
:func:`sim.virtual_sensor.write_sensor_images`)."""

from __future__ import annotations

from pipeline.base.registry import list_modes
from pipeline.cli._common import add_json_flag, print_json


def register(group):
    text = ("render a randomised virtual GelSight-type sensor's ball presses (drift, printed markers, JPEG, "
            "vignetting, column stripes; exact truth) as a capture file and/or a folder of images")
    p = group.add_parser("sensor", help=text, description=text)
    sensor = p.add_argument_group("sensor and presses")
    sensor.add_argument("--seed", type=int, default=0, help="which sensor (same seed, same sensor and frames)")
    sensor.add_argument("--shape", nargs=2, type=int, metavar=("H", "W"), help="image size (default: drawn)")
    sensor.add_argument("--presses", type=int, default=8, help="number of presses (default 8)")
    sensor.add_argument("--lights", default="gelsight", metavar="{" + ",".join(["gelsight", *list_modes()]) + "}",
                        help="gelsight (default) or a lighting mode of the 24-LED ring")
    sensor.add_argument("--effects", default="all", metavar="all|none|E1,E2",
                        help="markers, marker_motion (markers the presses move), vignetting, soft_shading (a soft "
                             "gel: weak, blurred shading and a glossy rim highlight), drift_gain, drift_offset, "
                             "drift_field, column_stripes, read_noise, jpeg (default all)")
    sensor.add_argument("--border-fraction", type=float, default=0.15, help="presses cut by the image border")
    outs = p.add_argument_group("what is written (--out, --images or both)")
    outs.add_argument("--out", metavar="capture.h5", help="write a capture file (calibrate reads it)")
    outs.add_argument("--images", metavar="DIR", help="write frame_*.jpg|png and labels.csv (import images reads it)")
    outs.add_argument("--labels", action="store_true", help="also store the true circles as hand labels (--out)")
    add_json_flag(outs)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pipeline.base.errors import UserError
    from sim.virtual_sensor import random_sensor, write_sensor_capture, write_sensor_images

    if not args.out and not args.images:
        raise UserError("sim sensor: give --out capture.h5, --images DIR, or both")
    effects = args.effects if args.effects in ("all", "none") else [e.strip() for e in args.effects.split(",")]
    try:
        s = random_sensor(args.seed, shape=args.shape, num_presses=args.presses, lights=args.lights, effects=effects,
                          border_fraction=args.border_fraction)
    except ValueError as exc:
        raise UserError(f"sim sensor: {exc}") from None
    res = {"sensor": s.to_dict(), "effects": list(s.effects), "ball_radius_px": s.ball_radius_px}
    if args.out:
        write_sensor_capture(args.out, s, labels=args.labels)
        res["out"] = str(args.out)
    if args.images:
        r = write_sensor_images(args.images, s)
        res.update(images=r["folder"], reference=r["reference"], labels_csv=r["labels"])
    if args.json:
        print_json(res)
        return 0
    h, w = s.shape
    where = " and ".join(x for x in (res.get("out"), res.get("images")) if x)
    print(f"wrote {where}: virtual sensor {args.seed}, {s.num_presses} presses, {h}x{w} px at {s.mm_per_px:.4f} mm/px, "
          f"ball {s.ball_radius_mm} mm ({s.ball_radius_px:.1f} px); effects {', '.join(s.effects) or 'none'}"
          + (f"; reference {res['reference']}" if args.images else ""))
    return 0
