"""``iristac sim modes|render|uniformity``: the renderer's commands.

Each calls one documented function: :func:`pipeline.base.modes.describe_modes`,
:func:`sim.rendered_capture.render_scene_files`, :func:`sim.uniformity.uniformity_report`
(+ :func:`sim.uniformity.uniformity_figure`).
"""

from __future__ import annotations

from pipeline.cli._common import add_json_flag, mode_metavar, print_json


def register(group):
    p = group.add_parser("modes", help="list the lighting modes", description="list the lighting modes")
    p.add_argument("files", nargs="*", metavar="MODE", help="mode names or user mode files (default: built-in)")
    add_json_flag(p)
    p.set_defaults(func=_modes)

    text = "render a height map (file or sphere) under a lighting mode to PNGs and a capture file"
    p = group.add_parser("render", help=text, description=text)
    what = p.add_argument_group("what presses the gel (one of --height and --sphere)")
    src = what.add_mutually_exclusive_group()
    src.add_argument("--height", metavar="FILE", help="height map: .npy or 16-bit .png")
    src.add_argument("--sphere", nargs=2, type=float, metavar=("RADIUS", "DEPTH"), help="a ball press (mm)")
    what.add_argument("--height-scale", type=float, default=1.0, help="mm per stored unit of --height (default 1)")
    what.add_argument("--center", nargs=2, type=float, default=(0.0, 0.0), metavar=("X", "Y"),
                      help="sphere centre, mm, reconstruction frame")
    light = p.add_argument_group("lighting and image grid")
    light.add_argument("--mode", default="monochromatic", metavar=mode_metavar(),
                       help="lighting mode: a built-in name or a mode file (default monochromatic)")
    light.add_argument("--illumination", metavar="ILL", help="illumination.h5 from `iristac sim synthesize` "
                       "(default: the closed-form bare LED ring at --gel-z); its grid sets the size and pitch")
    light.add_argument("--gel-z", type=float, default=35.0, help="LED plane to gel distance, mm (default 35)")
    light.add_argument("--shape", nargs=2, type=int, metavar=("H", "W"), help="image size (default 240 320)")
    light.add_argument("--mm-per-px", type=float, default=0.0625, help="pixel pitch on the gel (default 0.0625)")
    cam = p.add_argument_group("camera effects")
    cam.add_argument("--settings", metavar="FILE", help="render settings YAML (effects); see docs/renderer.md")
    cam.add_argument("--noise", type=float, default=1.0, help="read noise sigma in DN without --settings (default 1)")
    cam.add_argument("--bit-depth", type=int, default=8, choices=[8, 10, 12, 16], help="without --settings (default 8)")
    cam.add_argument("--seed", type=int, default=0, help="seed of the noise and effects (default 0)")
    outs = p.add_argument_group("what is written")
    outs.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_json_flag(outs)
    p.set_defaults(func=_render)

    text = "per-channel uniformity of each lighting mode on a flat gel (numbers and a figure)"
    p = group.add_parser("uniformity", help=text, description=text)
    p.add_argument("modes", nargs="*", metavar="MODE", help="modes (default: built-in)")
    p.add_argument("--shape", nargs=2, type=int, default=(120, 160), metavar=("H", "W"))
    p.add_argument("--mm-per-px", type=float, default=0.125)
    p.add_argument("--gel-z", type=float, default=35.0)
    p.add_argument("--illumination", metavar="ILL", help="illumination.h5 (default: the bare LED ring)")
    p.add_argument("--figure", metavar="PNG", help="write the figure here")
    add_json_flag(p)
    p.set_defaults(func=_uniformity)


def _modes(args) -> int:
    from pipeline.base.modes import describe_modes

    rows = describe_modes(args.files or None)
    if args.json:
        print_json({"modes": rows})
        return 0
    print(f"{'mode':<15} {'frames':>6} {'leds':>4}  description")
    for r in rows:
        print(f"{r['name']:<15} {r['frames']:>6} {r['leds']:>4}  {r['description']}")
    return 0


def _render(args) -> int:
    from sim.rendered_capture import render_scene_files

    res = render_scene_files(args.out, mode=args.mode, height_file=args.height, height_scale=args.height_scale,
                             sphere_rd=args.sphere, center=args.center, shape=args.shape,
                             mm_per_px=args.mm_per_px, gel_z=args.gel_z, settings_file=args.settings,
                             noise_dn=args.noise, bit_depth=args.bit_depth, seed=args.seed,
                             illumination=args.illumination)
    if args.json:
        print_json(res)
    else:
        print(f"{res['mode']}: {len(res['patterns'])} patterns, {res['shape'][0]}x{res['shape'][1]} px, "
              f"exposure {res['exposure']:.4g}, effects {', '.join(res['effects']) or 'none'}")
        print(f"wrote {res['capture']} and {len(res['pngs'])} PNGs in {args.out}")
    return 0


def _uniformity(args) -> int:
    from sim.render import bare_ring_illumination
    from sim.uniformity import uniformity_figure, uniformity_report

    if args.illumination:
        from sim.synthesize import load_illumination

        model = load_illumination(args.illumination)
    else:
        model = bare_ring_illumination(tuple(args.shape), args.mm_per_px, args.gel_z)
    rep = uniformity_report(model, args.modes or None)
    fig = str(uniformity_figure(model, args.figure, list(rep))) if args.figure else None
    if args.json:
        print_json({"modes": {k: v["channels"] for k, v in rep.items()}, "frames": {k: v["frames"] for k, v in rep.items()},
                    "figure": fig})
        return 0
    print(f"{'mode':<15} {'ch':<2} {'lit':>3} {'cv mean':>8} {'cv max':>8} {'min/max':>8}")
    for name, r in rep.items():
        for c, s in r["channels"].items():
            if s["frames_lit"]:
                print(f"{name:<15} {c:<2} {s['frames_lit']:>3} {s['cv_mean']:>8.4f} {s['cv_max']:>8.4f} "
                      f"{s['min_over_max_min']:>8.3f}")
            else:
                print(f"{name:<15} {c:<2} {0:>3} {'unlit':>8}")
    if fig:
        print(f"figure: {fig}")
    return 0
