"""``iristac bench NAME``: each benchmark is a module ``pipeline.bench.NAME`` with ``run()``.

A benchmark module exposes::

    def add_arguments(parser) -> None      # optional extra flags
    def run(args) -> dict                  # measures, returns JSON-able results
    def format_table(result: dict) -> str  # the human-readable side-by-side table

``report`` and ``compare`` follow the same protocol on saved runs (a result's ``exit_code``
becomes the command's).
"""

from __future__ import annotations

import importlib
import sys

from pipeline.cli._common import add_json_flag, make_group, print_json

BENCHMARKS = [
    ("sim", "ray tracer: rays x sampler, Newton iterations, multi-source methods, effect sets"),
    ("render", "renderer: frames per second per effect set and image size"),
    ("capture", "capture: pattern changes per second over the emulator"),
    ("reconstruct", "normals and depth: time and error per solver, integrator and size"),
    ("calibration", "calibration: time and cross-validated error per model"),
    ("live", "live paths: uint8 frames to heights per solver, size and thread count, fast vs eager"),
    ("batch", "batch processing: recordings on disk to results on disk, frames/s and peak memory against length, "
              "beside the live path"),
    ("codec", "frames storage: size, write and decode speed of each candidate codec on real and virtual frames"),
    ("lens", "lens optimizer: the lens targets, CMA-ES against random search and Nelder-Mead"),
    ("modes", "lighting modes: normal error against capture and reconstruction time per mode and solver"),
    ("all", "every benchmark; writes docs/benchmarks.md, .json, .html (the charts) and .png (their summary)"),
    ("report", "the charts of a saved run: an offline interactive page (and the summary figure)"),
    ("compare", "rows of two saved runs that got slower or less accurate beyond the noise (exit 1 if any)"),
]


#: Commands that read saved runs instead of measuring.
ON_SAVED_RUNS = ("report", "compare")


def register(sub, name, help_text):
    from pipeline.cli import _common

    _, group = make_group(sub, name, help_text)
    # Benchmarks import torch and friends; import one only when its own options are needed
    # (``iristac bench NAME ...``), so that every other command starts fast.
    wanted = _requested_bench(_common.ARGV)
    for bench_name, text in BENCHMARKS:
        p = group.add_parser(bench_name, help=text, description=text)
        add_json_flag(p)
        if bench_name not in ON_SAVED_RUNS:
            p.add_argument("--quick", action="store_true", help="smaller sizes, for a smoke test")
        if bench_name == wanted:
            module = _load(bench_name)
            if module is not None and hasattr(module, "add_arguments"):
                module.add_arguments(p)
        p.set_defaults(func=_runner(bench_name))


def _requested_bench(argv) -> str | None:
    """``NAME`` when the command line is ``[...] bench NAME ...``."""
    for i, a in enumerate(argv[:-1]):
        if a == "bench":
            return argv[i + 1]
    return None


def _load(bench_name):
    try:
        return importlib.import_module(f"pipeline.bench.{bench_name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"pipeline.bench.{bench_name}":
            return None
        raise


def _runner(bench_name):
    def run(args) -> int:
        module = _load(bench_name)
        if module is None:
            print(f"iristac bench {bench_name}: not implemented yet", file=sys.stderr)
            return 3
        result = module.run(args)
        if args.json:
            print_json(result)
        else:
            print(module.format_table(result))
        return int(result.get("exit_code", 0)) if isinstance(result, dict) else 0

    return run
