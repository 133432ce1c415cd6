"""The ``iristac`` command line: a thin layer over documented Python functions.

Each command group lives in its own module under ``pipeline/cli/`` and exposes
``register(subparsers)``; heavy libraries (torch, cv2) are imported inside the command
functions so that ``iristac --help`` stays fast.

Exit codes: 0 success, 1 the command ran and found a problem (e.g. bad cache entries),
2 bad usage or bad input, 3 not implemented yet.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from pipeline import __version__

# (command, module, one-line help). Order is the order shown by --help.
COMMANDS = [
    ("demo", "pipeline.cli.demo", "run the whole pipeline on a virtual IrisTac and write a report"),
    ("run", "pipeline.cli.run", "run the five cached stages from a pipeline config file"),
    ("sim", "pipeline.cli.sim", "ray tracer, renderer and lighting modes"),
    ("capture", "pipeline.cli.capture", "capture frames for a lighting mode from the LED ring and a camera"),
    ("emulate-ring", "pipeline.cli.emulate_ring", "run the LED-ring MCU emulator behind a pseudo-terminal"),
    ("calibrate", "pipeline.cli.calibrate", "fit light models from a sphere-indentation capture"),
    ("label", "pipeline.cli.label", "accept, move, resize or reject contact circles in a browser page"),
    ("reconstruct", "pipeline.cli.reconstruct", "normals and depth from a capture"),
    ("compare-modes", "pipeline.cli.compare_modes", "compare lighting modes by reconstruction error"),
    ("batch", "pipeline.cli.batch", "reconstruct many recorded captures with a shared calibration"),
    ("live", "pipeline.cli.live", "reconstruct a camera or the virtual sensor live (record, view in a browser)"),
    ("bench", "pipeline.cli.bench", "benchmarks that print error and time side by side"),
    ("cache", "pipeline.cli.cache", "inspect and maintain the stage store"),
    ("import", "pipeline.cli.importers", "import captures from other formats"),
    ("eval", "pipeline.cli.evaluate", "evaluate results against ground truth"),
    ("doctor", "pipeline.cli.doctor", "check the GPU stack and compile every GPU kernel once"),
]


def command_defaults(*argv: str) -> argparse.Namespace:
    """The options a command runs with when given only ``argv`` (e.g. ``"live", "--virtual"``):
    how a benchmark marks the shipped default without restating it."""
    return build_parser().parse_args(list(argv))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="iristac",
        description="IrisTac reconstruction: calibrate, synthesize, capture, normals, depth.",
    )
    parser.add_argument("--version", action="version", version=f"iristac {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name, help_text in COMMANDS:
        module = importlib.import_module(module_name)
        module.register(sub, name, help_text)
    return parser


def main(argv: list[str] | None = None) -> int:
    from pipeline.cli import _common

    _common.ARGV = list(sys.argv[1:] if argv is None else argv)
    _common.warnings_to_stderr()
    parser = build_parser()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        # A group given without its subcommand: show that group's help.
        helper = getattr(args, "group_parser", parser)
        helper.print_help(sys.stderr)
        return 2
    try:
        code = func(args)
    except KeyboardInterrupt:
        print("iristac: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the CLI turns known errors into one clear line
        from pipeline.base.errors import UserError

        if isinstance(exc, UserError):
            print(f"iristac {args.command}: error: {exc}", file=sys.stderr)
            return 2
        raise
    return 0 if code is None else int(code)
