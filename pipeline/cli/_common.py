"""Small helpers shared by the CLI modules."""

from __future__ import annotations

import json
import sys
from typing import Any

EXIT_NOT_IMPLEMENTED = 3

#: The arguments being parsed (set by :func:`pipeline.cli.main`), for commands that load
#: heavy modules only when they are the ones asked for.
ARGV: list[str] = []


def add_json_flag(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print results as JSON (stable keys)")


def print_json(obj: Any) -> None:
    json.dump(obj, sys.stdout, indent=2, sort_keys=True, default=_json_default)
    sys.stdout.write("\n")


def _json_default(obj):
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


def not_implemented(sub, name: str, help_text: str, issue: str):
    """Register a command that says plainly it does not exist yet and exits non-zero."""
    p = sub.add_parser(name, help=f"{help_text} [not implemented yet]", description=help_text)
    p.add_argument("rest", nargs="*", help=argparse_suppress())

    def run(args) -> int:
        print(f"iristac {name}: not implemented yet ({issue})", file=sys.stderr)
        return EXIT_NOT_IMPLEMENTED

    p.set_defaults(func=run)
    return p


def argparse_suppress():
    import argparse

    return argparse.SUPPRESS


def make_group(sub, name: str, help_text: str):
    """Create a command group; returns (parser, subparsers)."""
    p = sub.add_parser(name, help=help_text, description=help_text)
    p.set_defaults(group_parser=p)
    return p, p.add_subparsers(dest=f"{name}_command", metavar="SUBCOMMAND")
