"""``iristac batch RECORDINGS... --calibration CAL | --illumination ILL [--threads N | --workers N | --scheduler ADDRESS]``.

Calls :func:`pipeline.workflows.batch.batch_reconstruct` and prints
:func:`pipeline.workflows.task_pool.format_summary` (``--json``: :func:`pipeline.workflows.batch.summary_json`).
"""

from __future__ import annotations

import sys
import time

from pipeline.cli._common import (
    add_heal_flag,
    add_json_flag,
    add_light_flags,
    add_output_flags,
    add_solving_group,
    print_json,
)


def register(sub, name, help_text):
    from pipeline.frame_pipeline.outputs import DEFAULT_BATCH

    p = sub.add_parser(name, help=help_text, description=help_text)
    p.add_argument("recordings", nargs="+", metavar="RECORDING", help="capture.h5 files, videos (.mp4, .avi, ...) or folders of them")
    add_light_flags(p, "shared calibration.h5", "shared illumination.h5")
    solve = add_solving_group(p)
    solve.add_argument("--device", default="cpu", help="torch device of the eager solvers (cpu, cuda)")
    solve.add_argument("--match-colours", action="store_true",
                       help="bring each recording's colours to the calibration's by one gain per channel from its "
                            "no-contact frame (another unit's LEDs; the LUT's or MLP's stored reference)")
    where = p.add_argument_group("where it runs")
    where.add_argument("--threads", type=int, default=0,
                       help="threads of the frame pipeline in each process: frames in parallel (default 0: every "
                            "core)")
    procs = where.add_mutually_exclusive_group()
    procs.add_argument("--workers", type=int, default=1,
                       help="local worker processes, each a range of frames (default 1: this process)")
    procs.add_argument("--scheduler", metavar="ADDRESS",
                       help="Dask scheduler, e.g. tcp://host:8786: frame ranges over its workers (they must see "
                            "the same files and store)")
    where.add_argument("--connect-timeout", type=float, default=10.0, help="seconds to wait for the scheduler")
    outs = p.add_argument_group("what is written")
    add_output_flags(outs, DEFAULT_BATCH)
    outs.add_argument("--out", metavar="DIR", help="OUT/<recording>/normals.h5, depth.h5 (links to the store's "
                                                   "files, not copies)")
    outs.add_argument("--images", action="store_true", help="also write PNG/PLY pictures to --out")
    outs.add_argument("--cache", metavar="DIR", help="store folder (default: $IRISTAC_CACHE or ./iristac-cache)")
    outs.add_argument("--force", action="store_true", help="recompute even if the store has the results")
    add_heal_flag(outs)
    add_json_flag(outs)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pipeline.base.errors import UserError
    from pipeline.workflows.batch import SUMMARY_COLUMNS, batch_reconstruct, summary_json
    from pipeline.workflows.task_pool import format_summary

    if args.threads < 0:
        raise UserError(f"--threads must be 0 (every core) or more, got {args.threads}")
    t0 = time.perf_counter()
    items = batch_reconstruct(args.recordings, calibration=args.calibration, illumination=args.illumination,
                              solver=args.solver, integrator=args.integrator, out=args.out, store=args.cache,
                              images=args.images, device=args.device, workers=args.workers,
                              scheduler=args.scheduler, progress=not args.json and sys.stderr.isatty(),
                              connect_timeout=args.connect_timeout, heal=not args.no_heal, mask=args.mask,
                              markers=args.markers, threads=args.threads or None, drift=args.drift, save=args.save,
                              precision=args.precision, force=args.force, reference=args.reference,
                              mm_per_px=args.mm_per_px, match_colours=args.match_colours)
    summary = summary_json(items, time.perf_counter() - t0)
    if args.json:
        print_json(summary)
    else:
        print(format_summary(items, SUMMARY_COLUMNS))
        print(f"{summary['frames_solved']} frames solved at {summary['frames_per_second']:.1f} frames/s "
              f"({summary['solve_seconds']:.2f} s; start-up {summary['startup_seconds']:.2f} s), peak memory "
              f"{summary['peak_rss_mb']:.0f} MB")
    # Bad recordings are reported and skipped; the exit status says some were.
    return 1 if summary["failed"] else 0
