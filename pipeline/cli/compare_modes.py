"""``iristac compare-modes``: which lighting mode reconstructs best (:func:`pipeline.workflows.compare_modes.compare_modes`)."""

from __future__ import annotations

from pipeline.base.errors import UserError
from pipeline.cli._common import add_json_flag, add_solver_flags, mode_help, object_help, print_json


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text + ". Renders a test object under each mode "
                       "with the virtual sensor, or compares your own captures (each with truth/* datasets).")
    what = p.add_argument_group("what is compared")
    what.add_argument("--modes", nargs="+", metavar="MODE",
                      help=mode_help("lighting modes (default: every built-in)"))
    what.add_argument("--object", default="test-object",
                      help=object_help("test-object: the demo's ball, rod and punch"))
    what.add_argument("--captures", nargs="+", metavar="MODE=CAPTURE",
                      help="compare these captures instead of rendering")
    light = p.add_argument_group("light model (one of --scene and --illumination)")
    src = light.add_mutually_exclusive_group()
    src.add_argument("--scene", default="default", help="scene to trace (default: default)")
    src.add_argument("--illumination", metavar="ILL", help="use this illumination.h5 instead of tracing")
    light.add_argument("--rays", type=int, default=2_000_000, help="rays per LED when tracing")
    virt = p.add_argument_group("virtual sensor")
    virt.add_argument("--size", nargs=2, type=int, metavar=("H", "W"), default=(120, 160),
                      help="image size (default 120 160)")
    virt.add_argument("--mm-per-px", type=float, default=0.15, help="pixel pitch on the gel, mm (default 0.15)")
    virt.add_argument("--render-only", action="store_true",
                      help="render frames directly instead of capturing through the ring emulator and virtual camera")
    virt.add_argument("--faults", help="fault spec for the emulated ring, e.g. drop=0.05,corrupt=0.05")
    virt.add_argument("--fps", type=float, default=30.0, help="virtual camera frame rate (default 30)")
    solve = p.add_argument_group("solving")
    solve.add_argument("--calibration", nargs="+", metavar="MODE=CAL", help="calibrations with a lookup table per mode")
    solve.add_argument("--no-lut", action="store_true", help="do not calibrate lookup tables for single-frame modes")
    add_solver_flags(solve, solver=False, short_help=True)
    outs = p.add_argument_group("what is written")
    outs.add_argument("--out", required=True, help="folder for report.html, report.json and the captures")
    outs.add_argument("--cache", help="stage store folder (default: OUT/cache)")
    add_json_flag(outs)
    p.set_defaults(func=_run)


def _pairs(items, flag):
    out = {}
    for item in items or []:
        if "=" not in item:
            raise UserError(f"{flag}: expected MODE=PATH, got {item!r}")
        k, v = item.split("=", 1)
        out[k] = v
    return out


def _run(args) -> int:
    import sys

    from pipeline.workflows.compare_modes import compare_modes

    data = compare_modes(args.out, modes=args.modes, scene=args.scene, illumination=args.illumination,
                         object=args.object, shape=tuple(args.size), mm_per_px=args.mm_per_px, rays=args.rays,
                         captures=_pairs(args.captures, "--captures") or None,
                         calibrations=_pairs(args.calibration, "--calibration"), lut=not args.no_lut,
                         integrator=args.integrator, cache=args.cache, emulate=not args.render_only,
                         faults=args.faults, camera_fps=args.fps,
                         log=lambda m: print(f"[compare-modes] {m}", file=sys.stderr))
    if args.json:
        print_json(data)
        return 0
    print(f"{'mode':<14} {'solver':<10} {'patterns':>8} {'normal mean (deg)':>18} {'depth RMSE (mm)':>16} {'capture s':>10}")
    for r in data["comparison"]["runs"]:
        n, d = r["normal_mean_error_deg"], r["depth_rmse_mm"]
        print(f"{r['mode']:<14} {r['solver']:<10} {r['patterns']:>8} {('%.3f' % n) if n is not None else '-':>18} "
              f"{('%.4f' % d) if d is not None else '-':>16} {r['capture_seconds']:>10.3g}")
    best = data["comparison"]["best"]
    if best:
        print(f"best: {best['mode']} with {best['solver']} ({best['normal_mean_error_deg']:.3f} deg)")
    print(f"report: {args.out}/report.html")
    return 0
