"""``iristac demo``: the whole pipeline on a virtual IrisTac (see :func:`pipeline.workflows.demo.run_demo`)."""

from __future__ import annotations

from pipeline.cli._common import add_json_flag, print_json


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text)
    p.add_argument("--out", default="iristac-demo", help="output folder (default: iristac-demo)")
    p.add_argument("--cache", help="stage store folder (default: OUT/cache)")
    p.add_argument("--quick", action="store_true", help="smaller images and fewer rays (about 4x faster)")
    p.add_argument("--scene", default="default",
                   help="the virtual sensor's optics: a shipped scene or a scene file (default: default)")
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pipeline.workflows.demo import run_demo

    data = run_demo(args.out, quick=args.quick, cache=args.cache, progress=True, scene=args.scene)
    if args.json:
        print_json(data)
    else:
        print(_table(data))
        print(f"report: {args.out}/report.html")
    return 0


def _table(data) -> str:
    rows = data["comparison"]["runs"]
    lines = [f"{'mode':<14} {'solver':<10} {'normal mean (deg)':>18} {'depth RMSE (mm)':>16} {'recon s':>8} {'capture s':>10}"]
    for r in rows:
        n = r["normal_mean_error_deg"]
        d = r["depth_rmse_mm"]
        lines.append(f"{r['mode']:<14} {r['solver']:<10} {('%.3f' % n) if n is not None else '-':>18} "
                     f"{('%.4f' % d) if d is not None else '-':>16} {r['reconstruct_seconds']:>8.3f} "
                     f"{r['capture_seconds']:>10.3f}")
    lines.append(f"total {data['seconds']:.1f} s")
    return "\n".join(lines)
