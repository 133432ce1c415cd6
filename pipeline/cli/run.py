"""``iristac run CONFIG.yaml [--dry-run] [--force STAGE] [--json] [--cache DIR]``.

Calls :func:`pipeline.workflows.run.run_pipeline` (or :func:`pipeline.workflows.run.plan_pipeline` for
``--dry-run``).
"""

from __future__ import annotations

import sys

from pipeline.cli._common import add_heal_flag, add_json_flag, print_json


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text)
    p.add_argument("config", help="pipeline config YAML (data_schemas/configs/pipeline.json)")
    p.add_argument("--dry-run", action="store_true", help="list what would be recomputed and why; compute nothing")
    p.add_argument("--force", action="append", default=[], metavar="STAGE",
                   help="recompute STAGE and every stage downstream of it (repeatable)")
    p.add_argument("--cache", default=None, help="stage store folder (overrides the config's 'cache')")
    p.add_argument("--out", default=None, help="output folder (overrides the config's 'out')")
    p.add_argument("--device", default=None, help="torch device (overrides the config's 'device')")
    add_heal_flag(p)
    p.add_argument("--quiet", action="store_true", help="no per-stage lines or progress bars on stderr")
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pipeline.stages.graph import StageFailed
    from pipeline.workflows.run import plan_pipeline, run_pipeline

    if args.dry_run:
        plan = plan_pipeline(args.config, cache=args.cache, force=args.force)
        if args.json:
            print_json({"stages": plan})
            return 0
        for s in plan:
            print(f"{s['name']:<11} {'cached' if s['cached'] else 'RUN':<7} {s['reason']}")
        return 0
    try:
        report = run_pipeline(args.config, cache=args.cache, out=args.out, force=args.force,
                              device=args.device,
                              progress=not (args.quiet or args.json), heal=not args.no_heal)
    except StageFailed as exc:
        if args.json:  # what ran before the failure, then the one-line error on stderr
            print_json({"stages": [r.to_json() for r in exc.results], "error": str(exc)})
        raise
    if args.json:
        print_json(report.to_json())
        return 0
    print(f"{'stage':<11} {'status':<9} {'seconds':>8}  key")
    for s in report.stages:
        print(f"{s['name']:<11} {'cached' if s['cached'] else 'computed':<9} {s['seconds']:>8.3f}  {s['key'][:16]}")
    extra = "  ".join(f"{k} {v:.4g}" for k, v in report.summary.items() if isinstance(v, float))
    print(f"total {report.seconds:.2f} s" + (f"; {extra}" if extra else ""), file=sys.stdout)
    if report.outputs:
        print(f"wrote {len(report.outputs)} files to {report.outputs[-1].rsplit('/', 1)[0]}")
    return 0
