"""``iristac demo``: the whole pipeline on a virtual IrisTac, ending in an HTML report.

1. **synthesize**: trace a scene (the shipped ``default``: LED ring + lens) onto the camera
   grid (cached in the stage store).
2. **calibrate**: render a sphere-indentation capture (a 4 mm ball pressed at several places,
   every LED in turn, 8-bit, 1 DN noise), detect the contacts and fit light models with
   cross-validation; for the single-frame modes also a colour lookup table.
3. **capture**: the test object (a textured ball, a rod and a flat punch pressed at once) under
   every shipped lighting mode.
4. **normals** and 5. **depth**: every applicable solver per mode, DST Poisson integration.

Every stage goes through the stage registry (:mod:`pipeline.stages`) and the store in
``out/cache`` (or ``--cache``): a second demo reads back what the first computed, and the
same work asked for by ``iristac run`` or ``compare-modes`` is the same cache entry.

The report (``report.html`` + ``report.json``) shows the frames, normal maps, depth maps and
error maps per mode and solver, with a table of errors and times and two interactive charts
(normal error against capture time and against reconstruction time, Pareto front drawn,
:mod:`pipeline.charts`); ``summary.png`` has the same two charts as a 900 px figure.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, Callable

__all__ = ["run_demo", "DemoSettings"]


class DemoSettings:
    """Sizes of the demo; ``quick`` is a smaller version for tests."""

    def __init__(self, quick: bool = False):
        self.quick = quick
        self.shape = (60, 80) if quick else (120, 160)
        self.mm_per_px = 0.3 if quick else 0.15
        self.rays = 300_000 if quick else 2_000_000
        self.ball_radius_mm = 2.0
        self.presses = 6 if quick else 10
        self.modes = builtin_modes()
        self.noise_dn = 1.0
        self.bit_depth = 8
        self.faults = "drop=0.02,corrupt=0.02"  # the link is not perfect; capture must still label every frame
        self.camera_fps = 60.0  # the virtual camera's frame rate


def builtin_modes() -> tuple[str, ...]:
    """Every built-in lighting mode (:func:`pipeline.base.registry.list_modes`), most patterns
    first: a new mode file is in the demo without a code change.

    Examples
    --------
    >>> builtin_modes()[0], {"trichromatic", "multicolour"} <= set(builtin_modes())
    ('point', True)
    """
    from pipeline.base.modes import load_mode
    from pipeline.base.registry import list_modes

    return tuple(sorted(list_modes(), key=lambda m: (-len(load_mode(m).frames), m)))


def _or(value, fallback):
    """A table cell: ``value``, or ``fallback`` (a reason, a dash) when it is None."""
    return fallback if value is None else value


def _summary_figure(comp, path: Path) -> str:
    """The comparison's charts (error against capture and reconstruction time) as one PNG."""
    from pipeline.charts.static import summary_figure
    from pipeline.workflows.compare_modes import comparison_charts

    return summary_figure(comparison_charts(comp), path, cols=2, width_px=900,
                          title="Lighting modes and solvers: what accuracy costs in time (iristac demo)")["path"]


def run_demo(out: str | Path = "iristac-demo", *, quick: bool = False, cache: str | Path | None = None,
             progress: bool = True, log: Callable[[str], None] | None = None,
             scene: str | Path = "default") -> dict[str, Any]:
    """Run the demo and write ``report.html`` and ``report.json`` into ``out``.

    Parameters
    ----------
    out : path
        Output folder (created).
    quick : bool
        Smaller images, fewer rays and presses (for tests; about 4x faster).
    cache : path, optional
        Stage store folder; default ``out/cache``, so a second run reuses the illumination and
        reconstructions.
    progress : bool
        Print one line per step on stderr.
    log : callable, optional
        Receives the progress lines instead of stderr.
    scene : str or path
        The virtual sensor's optics (a shipped scene's name or a scene file), e.g.
        ``"default-v1"`` for the lens before the optimized one.

    Returns
    -------
    dict
        The content of ``report.json``: per-stage seconds, calibration figures, and per mode and
        solver the normal and depth errors and times.
    """
    from pipeline.base.store import StageStore
    from pipeline.stages import synthesize as synthesize_stage
    from pipeline.workflows.compare_modes import compare_captures, render_mode_captures
    from sim.uniformity import uniformity_report

    t_start = time.perf_counter()
    settings = DemoSettings(quick)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    store = StageStore(cache if cache is not None else out / "cache")
    say = log or ((lambda m: print(f"[demo {time.perf_counter() - t_start:6.1f}s] {m}", file=sys.stderr))
                  if progress else (lambda m: None))
    stages: dict[str, dict[str, Any]] = {}
    # 1. synthesize -------------------------------------------------------------------------
    t0 = time.perf_counter()
    say(f"synthesize: tracing the {scene} scene, {settings.rays:,} rays per LED onto {settings.shape}")
    model, ill_key, ill_cached = synthesize_stage.run(store, scene, settings.shape, settings.mm_per_px,
                                                      rays=settings.rays, sampler="sobol")
    ill_path = store.path_for(ill_key)
    stages["synthesize"] = {"seconds": time.perf_counter() - t0, "cached": ill_cached, "key": ill_key.digest,
                            "path": str(ill_path), "rays_per_led": settings.rays, "sampler": "sobol",
                            "fraction_on_grid": model.meta.get("fraction_on_grid")}
    uniformity = uniformity_report(model, list(settings.modes))

    # 2. calibrate --------------------------------------------------------------------------
    stages["calibrate"], cal_summary, luts, presses = _demo_calibrate(store, model, ill_key, settings, out, say)

    # 3. capture ----------------------------------------------------------------------------
    t0 = time.perf_counter()
    say(f"capture: the test object under {', '.join(settings.modes)} through the ring emulator (pty, "
        f"{settings.faults}) and the virtual camera")
    captures, capture_seconds = render_mode_captures(store, model, ill_key, settings.modes, "test-object",
                                                     out / "captures", noise_dn=settings.noise_dn,
                                                     camera_fps=settings.camera_fps, emulate=True,
                                                     faults=settings.faults)
    stages["capture"] = {"seconds": time.perf_counter() - t0, "modes": list(settings.modes)}

    # 4 + 5. normals and depth --------------------------------------------------------------
    t0 = time.perf_counter()
    comp = compare_captures(captures, illumination=ill_path, calibrations=luts, capture_seconds=capture_seconds,
                            integrator="dst", store=store, out=out / "runs", progress=say)
    stages["reconstruct"] = {"seconds": time.perf_counter() - t0, "runs": len(comp.runs)}

    # report -------------------------------------------------------------------------------
    say("report: writing report.html and report.json")
    total = time.perf_counter() - t_start
    data = {"settings": {"scene": str(scene), "shape": list(settings.shape), "mm_per_px": settings.mm_per_px, "rays": settings.rays,
                         "ball_radius_mm": settings.ball_radius_mm, "presses": settings.presses,
                         "noise_dn": settings.noise_dn, "bit_depth": settings.bit_depth, "quick": quick},
            "stages": stages, "uniformity": {m: r["channels"] for m, r in uniformity.items()}, "comparison": comp.to_json(), "seconds": total,
            "calibration": {k: v for k, v in cal_summary.items() if k != "circles"}}
    _write_demo_report(out, data, scene, settings, stages, cal_summary, uniformity, comp, ill_cached, len(presses))
    say(f"done in {total:.1f} s: open {out / 'report.html'}")
    return data


def _demo_calibrate(store, model, ill_key, settings: DemoSettings, out: Path, say):
    """Stage 2 of the demo: a rendered ball-press capture calibrated with the far, near and traced
    models (``calibration.h5`` in ``out``), and a colour lookup table per single-frame mode.
    ``(stage entry of report.json, calibration summary, LUT calibrations, presses)``."""
    from pipeline.base.capture import write_capture
    from pipeline.base.store import Record, write_record
    from pipeline.stages import calibrate as calibrate_stage
    from pipeline.workflows.compare_modes import lut_calibrations
    from sim.rendered_capture import press_ring, render_capture, sphere_presses

    t0 = time.perf_counter()
    depths, centres = press_ring(settings.shape, settings.mm_per_px, settings.presses)
    presses = sphere_presses(settings.shape, settings.mm_per_px, settings.ball_radius_mm, depths, centres)
    say(f"calibrate: {len(presses)} rendered ball presses under every LED in turn")
    cal_cap = render_capture(model, "point", presses, noise_dn=settings.noise_dn, bit_depth=settings.bit_depth,
                             seed=11)
    write_capture(out / "calibration_capture.h5", Record(cal_cap.schema, cal_cap.data, cal_cap.meta))
    # Centre refinement votes with the traced model (refine_model="auto" with an illumination
    # model): on the quick demo with the previous default lens (scene default-v1) traced CV 0.69 deg
    # refined vs 1.01 deg unrefined; the polynomial near field (15 deg there: it cannot follow that
    # lens's sharp LED footprints) made it 2.9 deg. With the current default: traced 0.18 deg.
    cal, _, cal_cached = calibrate_stage.run(store, cal_cap, ball_radius_mm=settings.ball_radius_mm,
                                             models=["far", "near", "traced"], illumination=model,
                                             illumination_key=ill_key)
    write_record(out / "calibration.h5", Record(cal.schema, cal.data, cal.meta))
    cal_summary = cal.meta["summary"]
    say("calibrate: colour lookup tables for the single-frame modes")
    lut_skipped: dict[str, str] = {}
    luts = lut_calibrations(store, model, settings.modes, out, ball_radius_mm=settings.ball_radius_mm,
                            presses=presses, noise_dn=settings.noise_dn, bit_depth=settings.bit_depth,
                            skipped=lut_skipped)
    for m, why in lut_skipped.items():
        say(f"calibrate: no lookup table for {m}: {why}")
    stage = {"seconds": time.perf_counter() - t0, "presses": len(presses), "cached": cal_cached,
             "accepted": int(cal_summary.get("accepted", 0)),
             "models": cal_summary.get("models", {}), "lut_skipped": lut_skipped}
    return stage, cal_summary, luts, presses


def _write_demo_report(out: Path, data: dict, scene, settings: DemoSettings, stages: dict, cal_summary: dict,
                       uniformity: dict, comp, ill_cached: bool, presses: int) -> None:
    """``report.html`` and ``report.json`` (``data``, plus the summary figure) in ``out``: the
    stages, the calibration's CV, the flat-gel uniformity per mode and the comparison."""
    from pipeline.results.report import Report
    from pipeline.workflows.compare_modes import add_to_report

    total = data["seconds"]
    report = Report("IrisTac demo: a virtual sensor end to end",
                    f"Scene {scene} traced onto {settings.shape[1]}x{settings.shape[0]} pixels at "
                    f"{settings.mm_per_px} mm/px; calibrated from {presses} rendered ball presses; a test "
                    f"object captured under {len(settings.modes)} lighting modes (8-bit, 1 DN read noise) and "
                    f"reconstructed with every applicable solver. Total {total:.1f} s.")
    s = report.section("Stages")
    s.table(["stage", "seconds", "notes"],
            [["synthesize", stages["synthesize"]["seconds"],
              ("cached" if ill_cached else f"{settings.rays:,} Sobol rays per LED, hit rotation")],
             ["calibrate", stages["calibrate"]["seconds"],
              f"{stages['calibrate']['accepted']}/{presses} presses accepted"],
             ["capture", stages["capture"]["seconds"],
              f"ring emulator on a pty ({settings.faults}) + virtual camera at {settings.camera_fps:g} fps"],
             ["normals + depth", stages["reconstruct"]["seconds"], f"{len(comp.runs)} reconstructions"]])
    cs = report.section("Calibration (leave-presses-out cross-validation)")
    cs.table(["model", "CV mean (deg)", "CV median (deg)", "seconds"],
             [[name, _or(m.get("cv_mean_angular_error_deg"), m.get("note") or m.get("skipped")),
               _or(m.get("cv_median_angular_error_deg"), "–"), m.get("seconds", "–")]
              for name, m in cal_summary.get("models", {}).items()])
    us = report.section("Flat-gel uniformity per mode (per channel after channel separation)")
    us.table(["mode", "channel", "frames lit", "mean CV (std/mean)", "worst CV", "worst min/max"],
             [[mode, ch, st.get("frames_lit"), st.get("cv_mean", "–"), st.get("cv_max", "–"),
               st.get("min_over_max_min", "–")]
              for mode, r in uniformity.items() for ch, st in r["channels"].items()])
    add_to_report(report, comp)
    data["summary_figure"] = _summary_figure(comp, out / "summary.png")
    report.write(out, data=data)
