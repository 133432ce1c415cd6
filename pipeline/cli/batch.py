"""``iristac batch RECORDINGS... --calibration CAL | --illumination ILL [--workers N | --scheduler ADDRESS]``.

Calls :func:`pipeline.batch_reconstruct.batch_reconstruct` and prints
:func:`pipeline.batch.format_summary`.
"""

from __future__ import annotations

from pipeline.cli._common import (
    add_drift_flag,
    add_heal_flag,
    add_json_flag,
    add_markers_flag,
    add_mask_flag,
    add_solver_flags,
    add_threads_flag,
    print_json,
    threads_arg,
)


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text)
    p.add_argument("recordings", nargs="+", metavar="RECORDING", help="capture.h5 files or folders of them")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--calibration", metavar="CAL", help="shared calibration.h5")
    src.add_argument("--illumination", metavar="ILL", help="shared illumination.h5")
    add_solver_flags(p)
    add_mask_flag(p)
    add_markers_flag(p)
    add_drift_flag(p)
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="Dask scheduler, e.g. tcp://host:8786 (workers must see the same files)")
    p.add_argument("--connect-timeout", type=float, default=10.0, help="seconds to wait for the scheduler")
    p.add_argument("--out", metavar="DIR", help="write OUT/<recording>/normals.h5, depth.h5 (and pictures)")
    p.add_argument("--images", action="store_true", help="also write PNG/PLY pictures to --out")
    p.add_argument("--cache", metavar="DIR", help="store folder (default: $IRISTAC_CACHE or ./iristac-cache)")
    p.add_argument("--device", default="cpu", help="torch device (cpu, cuda)")
    add_threads_flag(p, "threads within each recording: torch's while solving; "
                   "with more than one, nearfield/lstsq on integer frames and dst depth take their batch fast paths, "
                   "every contact instance at once (default 1; 0: every core)")
    add_heal_flag(p)
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pipeline.batch import format_summary
    from pipeline.batch_reconstruct import SUMMARY_COLUMNS, batch_reconstruct

    threads = threads_arg(args)
    items = batch_reconstruct(args.recordings, calibration=args.calibration, illumination=args.illumination,
                              solver=args.solver, integrator=args.integrator, out=args.out, store=args.cache,
                              images=args.images, device=args.device, workers=args.workers,
                              scheduler=args.scheduler, progress=not args.json,
                              connect_timeout=args.connect_timeout, heal=not args.no_heal, mask=args.mask,
                              markers=args.markers, threads=threads, drift=args.drift)
    failed = sum(not i.ok for i in items)
    if args.json:
        print_json({"items": [i.to_json() for i in items], "processed": len(items) - failed, "failed": failed})
    else:
        print(format_summary(items, SUMMARY_COLUMNS))
    # Bad recordings are reported and skipped; the exit status says some were.
    return 1 if failed else 0
