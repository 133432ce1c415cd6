"""Small helpers shared by the CLI modules."""

from __future__ import annotations

import json
import sys
from typing import Any

EXIT_NOT_IMPLEMENTED = 3

#: The arguments being parsed (set by :func:`pipeline.cli.main`), for commands that load
#: heavy modules only when they are the ones asked for.
ARGV: list[str] = []


def add_solver_flags(parser, *, solver: bool = True, integrator: bool = True, default_solver: str = "lstsq",
                     short_help: bool = False) -> None:
    """``--solver`` and ``--integrator``, with the choices of their registries
    (:mod:`pipeline.base.registry`).

    ``parser`` is a parser or one of its argument groups (``parser.add_argument_group``).
    ``short_help``: show the choices in the usage line (``--solver {lstsq,nearfield,...}``) and a
    one-line help pointing to docs/reconstruction.md, instead of a ``SOLVER`` metavar and the
    registry's paragraph (the default)."""
    from pipeline.base.registry import INTEGRATORS, SOLVERS

    if solver:
        if short_help:
            parser.add_argument("--solver", choices=SOLVERS.names(), default=default_solver,
                                help=f"photometric-stereo solver (default {default_solver}; what each one does: "
                                     "docs/reconstruction.md, Normal solvers)")
        else:
            parser.add_argument("--solver", choices=SOLVERS.names(), default=default_solver, metavar="SOLVER",
                                help=f"photometric-stereo solver (default {default_solver}): {SOLVERS.help()}")
    if integrator:
        if short_help:
            parser.add_argument("--integrator", choices=INTEGRATORS.names(), default="dst",
                                help="depth integrator (default dst; what each one does: docs/reconstruction.md, "
                                     "Depth integrators)")
        else:
            parser.add_argument("--integrator", choices=INTEGRATORS.names(), default="dst", metavar="INTEGRATOR",
                                help=f"depth integrator (default dst): {INTEGRATORS.help()}")


def add_mask_flag(parser) -> None:
    """``--mask FILE``: the pixels to reconstruct (``reconstruct``, ``batch``).

    ``parser`` is a parser or one of its argument groups (``parser.add_argument_group``)."""
    parser.add_argument("--mask", metavar="FILE.png",
                        help="reconstruct only these pixels (PNG/NPY, non-zero inside; replaces the capture's mask)")


def add_markers_flag(parser) -> None:
    """``--markers auto|none|MASK.png``: printed gel markers to fill in (``reconstruct``, ``batch``, ``live``).

    ``parser`` is a parser or one of its argument groups (``parser.add_argument_group``)."""
    parser.add_argument("--markers", default=None, metavar="auto|none|MASK.png",
                        help="printed gel markers: filled in before normals are solved, invalid in the mask, "
                             "integrated through (auto: found in the reference; default: the capture's own, else "
                             "the calibration's)")


def add_video_flags(parser) -> None:
    """``--reference N|build`` and ``--mm-per-px MM`` of a video recording (``reconstruct``, ``batch``;
    :mod:`pipeline.capture.video_frames`); a parser or one of its argument groups."""
    parser.add_argument("--reference", metavar="N|build",
                        help="videos: the no-contact frame's index (default 0, the first frame; it is not a frame "
                             "of the results), or 'build' it from a sample of the frames")
    parser.add_argument("--mm-per-px", type=float, metavar="MM",
                        help="videos: the pixel pitch (default: the calibration's or illumination's)")


def add_drift_flag(parser) -> None:
    """``--drift auto|none|offset|gain_offset|field``: the illumination drift removed before the
    solve (``reconstruct``, ``batch``, ``live``; :mod:`pipeline.normals.drift`).

    ``parser`` is a parser or one of its argument groups (``parser.add_argument_group``)."""
    from pipeline.normals.drift import DRIFT_CHOICES

    parser.add_argument("--drift", choices=DRIFT_CHOICES, default="auto",
                        help="illumination drift against the no-contact reference, fitted on the pixels outside the "
                             "contact and removed before the solve (default auto: a per-channel gain and offset "
                             "where the solver keys on the reference: the calibration's models and --ratio; none: "
                             "off)")


def add_calibration_drift_flag(parser, help_text: str) -> None:
    """``--drift none|offset|gain_offset|field`` of ``calibrate`` and ``eval calibration``: the drift
    removed from each press outside its contact (:class:`calibration.detect.DetectOptions`);
    read it back with :func:`drift_options`.

    ``parser`` is a parser or one of its argument groups (``parser.add_argument_group``)."""
    from pipeline.normals.drift import DRIFT_MODELS

    parser.add_argument("--drift", choices=DRIFT_MODELS, default=None, help=help_text)


def drift_options(drift: str | None):
    """Detection options removing ``drift`` (None: None, the callee's default)."""
    if drift is None:
        return None
    from calibration.detect import DetectOptions

    return DetectOptions(drift=drift)


def add_threads_flag(parser, help_text: str) -> None:
    """``--threads N`` (default 1; 0: every core); read it back with :func:`threads_arg`.

    ``parser`` is a parser or one of its argument groups (``parser.add_argument_group``)."""
    parser.add_argument("--threads", type=int, default=1, help=help_text)


def threads_arg(args) -> int | None:
    """``--threads`` as the Python API takes it (None: every core), or a UserError when negative."""
    if args.threads < 0:
        from pipeline.base.errors import UserError

        raise UserError(f"--threads must be 0 (every core) or more, got {args.threads}")
    return args.threads or None


def mode_help(what: str = "lighting mode") -> str:
    """Help text naming the built-in lighting modes (:func:`pipeline.base.registry.list_modes`)."""
    from pipeline.base.registry import list_modes

    return f"{what}: a built-in name ({', '.join(list_modes())}) or a mode file"


def mode_metavar() -> str:
    """Metavar of a ``--mode`` that takes a built-in name or a file: ``{monochromatic,...}|FILE``
    (:func:`pipeline.base.registry.list_modes`), so the usage line shows the names."""
    from pipeline.base.registry import list_modes

    return "{" + ",".join(list_modes()) + "}|FILE"


def profile_metavar() -> str:
    """Metavar of a ``--profile`` that takes a built-in sensor profile or a file:
    ``{digit,gelsight-mini,iristac-ring}|FILE`` (:func:`pipeline.capture.sensor_profiles.list_profiles`)."""
    from pipeline.capture.sensor_profiles import list_profiles

    return "{" + ",".join(list_profiles()) + "}|FILE"


def object_help(default: str) -> str:
    """Help text naming the contact objects (:data:`sim.contacts.OBJECTS`)."""
    from sim.contacts import OBJECTS

    return (f"what presses the gel: {', '.join(OBJECTS)} (sim.contacts), or a .npy height map (H, W) or stack "
            f"(K, H, W) in mm, or a .png height map (default {default})")


def add_heal_flag(parser) -> None:
    """``--no-heal``: stop on a corrupt cache entry instead of quarantining and recomputing it.

    ``parser`` is a parser or one of its argument groups (``parser.add_argument_group``)."""
    parser.add_argument("--no-heal", action="store_true",
                        help="stop on a corrupt or schema-violating cache entry instead of quarantining it "
                             "(moved aside, never deleted) and recomputing it")


def warnings_to_stderr() -> None:
    """Warnings of the ``iristac`` logger (e.g. a healed cache entry) as one line each on stderr."""
    import logging

    log = logging.getLogger("iristac")
    if not log.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("iristac: warning: %(message)s"))
        log.addHandler(handler)
        log.propagate = False


def add_json_flag(parser) -> None:
    """``--json``; ``parser`` is a parser or one of its argument groups (``parser.add_argument_group``)."""
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


def add_output_flags(parser, default_save: str) -> None:
    """``--save`` and ``--precision``: what ``reconstruct`` and ``batch`` write beside the normals,
    heights and masks (:class:`pipeline.frame_pipeline.outputs.OutputSpec`); a parser or a group."""
    from pipeline.frame_pipeline.outputs import OUTPUT_CHOICES, PRECISIONS

    parser.add_argument("--save", default=default_save, metavar="{" + ",".join(OUTPUT_CHOICES) + ",all,none}",
                        help=f"outputs beside the normals, heights and masks, comma-separated (default "
                             f"{default_save}; contact costs about 10 ms a 320 x 240 frame, confidence 0.3 MB); "
                             f"docs/reconstruction.md")
    parser.add_argument("--precision", choices=list(PRECISIONS), default="single",
                        help="normals and confidence as float32 (single, default) or float16 (half)")


def add_light_flags(parser, calibration_help: str, illumination_help: str):
    """``--calibration CAL | --illumination ILL`` in a group of their own; returns the group."""
    light = parser.add_argument_group("light model (one of --calibration and --illumination)")
    src = light.add_mutually_exclusive_group()
    src.add_argument("--calibration", metavar="CAL", help=calibration_help)
    src.add_argument("--illumination", metavar="ILL", help=illumination_help)
    return light


def add_solving_group(parser):
    """The ``solving`` group ``reconstruct`` and ``batch`` share: solver, integrator, mask, markers,
    drift and the video flags; returns the group."""
    solve = parser.add_argument_group("solving")
    add_solver_flags(solve, short_help=True)
    add_mask_flag(solve)
    add_markers_flag(solve)
    add_drift_flag(solve)
    add_video_flags(solve)
    return solve


def shipped_calibration(command: str, profile, calibration, illumination):
    """The calibration ``live`` and ``reconstruct`` use with ``--profile`` and no light model of
    the user's: the one shipped with the profile (:mod:`pipeline.capture.shipped`), announced on
    stderr with its measured error on another unit (also with ``--json``); None where the user
    gave ``--calibration`` or ``--illumination``, or no calibration ships with the profile."""
    if profile is None or calibration is not None or illumination is not None:
        return None
    from pipeline.capture.sensor_profiles import load_profile
    from pipeline.capture.shipped import shipped_calibration_path, shipped_note

    path = shipped_calibration_path(load_profile(profile))
    if path is None:
        return None
    print(f"iristac {command}: no --calibration given: using the {shipped_note(path)}", file=sys.stderr, flush=True)
    return path
