"""``iristac bench modes``: what a lighting mode buys, in normal error against capture and reconstruction time.

The ``compare-modes`` run of the virtual sensor (:func:`pipeline.workflows.compare_modes.compare_modes`): the
shipped ``default`` scene traced onto the demo's camera grid, the demo's test object (a
textured ball, a rod and a flat punch) captured under every shipped lighting mode through
the ring emulator on a pseudo-terminal and the virtual camera at the demo's frame rate
(capture time measured: dark, reference and contact frames), lookup tables calibrated for
the single-frame modes, and every applicable solver per mode. Rows: per (mode, solver) the
mean normal error (deg), the reconstruction seconds (best of ``--repeats`` runs of the same
reconstructions, every run kept) and the capture seconds. The shipped default ringed is
what ``iristac live`` runs (its default mode and solver).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["add_arguments", "run", "format_table", "live_defaults"]


def add_arguments(parser) -> None:
    parser.add_argument("--repeats", type=int, default=None, help="reconstruction runs per mode and solver (default 3)")
    parser.add_argument("--rays", type=int, default=None, help="rays per LED of the trace (default: the demo's)")


def live_defaults() -> tuple[str, str]:
    """``iristac live``'s default mode and solver, read from its command line."""
    from pipeline.cli import command_defaults
    from pipeline.cli.live import chosen_solver
    from pipeline.live.session import DEFAULT_MODE

    a = command_defaults("live", "--virtual")
    return a.mode or DEFAULT_MODE, chosen_solver(a)


def run(args) -> dict:
    from pipeline.workflows.compare_modes import compare_captures, compare_modes, comparison_rows
    from pipeline.workflows.demo import DemoSettings

    quick = bool(getattr(args, "quick", False))
    st = DemoSettings(quick)
    repeats = getattr(args, "repeats", None) or (2 if quick else 3)
    rays = getattr(args, "rays", None) or st.rays
    load = list(os.getloadavg())
    with tempfile.TemporaryDirectory(prefix="iristac-bench-modes-") as d:
        data = compare_modes(d, modes=list(st.modes), shape=st.shape, mm_per_px=st.mm_per_px, rays=rays,
                             camera_fps=st.camera_fps, emulate=True, noise_dn=st.noise_dn)
        runs = {(r["mode"], r["solver"]): r for r in data["comparison"]["runs"]}
        times = {k: [r["reconstruct_seconds"]] for k, r in runs.items()}
        caps = {p.stem: p for p in sorted((Path(d) / "captures").glob("*.h5"))}
        cals = {p.stem.removeprefix("calibration_"): p for p in Path(d).glob("calibration_*.h5")}
        for _ in range(repeats - 1):
            again = compare_captures(caps, illumination=data["illumination"], calibrations=cals, integrator="dst",
                                     store=Path(d) / "cache")
            for r in again.runs:
                times.setdefault((r.mode, r.solver), []).append(r.reconstruct_seconds)
    for k, r in runs.items():
        r["reconstruct_seconds"] = min(times[k])
    rows = comparison_rows(list(runs.values()), default=live_defaults())
    for row in rows:
        row["seconds_runs"] = times[(row["mode"], row["solver"])]
    return {"rows": rows, "repeats": repeats, "rays": rays, "shape": list(st.shape), "camera_fps": st.camera_fps,
            "load_average": load + list(os.getloadavg())}


def format_table(result: dict) -> str:
    la = result["load_average"]
    lines = [f"bench modes: {result['shape'][1]}x{result['shape'][0]} px, {result['rays']:,} rays per LED, camera "
             f"{result['camera_fps']:g} fps, reconstruction best of {result['repeats']}; load average {la[0]:.2f} "
             f"before, {la[3]:.2f} after",
             f"{'mode':<14}{'solver':<11}{'patterns':>9}{'normal err deg':>15}{'reconstruct s':>14}{'capture s':>11}"]
    for r in result["rows"]:
        lines.append(f"{r['mode']:<14}{r['solver']:<11}{r['patterns']:>9}{r['error']:>15.3f}{r['seconds']:>14.3f}"
                     f"{r['capture_seconds']:>11.3f}{'  (default: iristac live)' if r['default'] else ''}")
    return "\n".join(lines)
