"""``iristac sim trace|section|optimize-lens|synthesize``: the ray tracer's commands.

Each command parses its options and calls one documented function:
``trace`` -> :func:`sim.lens_design.trace_report`, ``section`` -> :func:`sim.section.draw_section`,
``optimize-lens`` -> :func:`sim.lens_design.optimize_lens`, ``synthesize`` ->
:func:`pipeline.stages.synthesize.run`.
"""

from __future__ import annotations

from pipeline.base.errors import UserError
from pipeline.cli._common import add_json_flag, print_json

SAMPLERS = ("grid", "random", "stratified", "sobol")
METHODS = ("hits", "image", "trace")


def register(group):
    _add_trace(group)
    _add_section(group)
    _add_optimize_lens(group)
    _add_synthesize(group)


def _add_trace(group) -> None:
    """``sim trace``: flux on screen and uniformity of a scene."""
    p = group.add_parser("trace", help="trace a scene and report flux on screen and uniformity",
                         description="Trace every LED of a scene onto its imaging plane; print the fraction of "
                                     "light on screen, mean intensity and uniformity (the paper's figures).")
    p.add_argument("scene", help="shipped scene name (default, plano-sphere) or a YAML path")
    rays = p.add_argument_group("rays and lens")
    run = p.add_argument_group("where it runs")
    _trace_options(rays, run)
    rays.add_argument("--no-lens", action="store_true", help="trace without the lens (the paper's comparison)")
    rays.add_argument("--intersection", choices=("robust", "paper"), default=None,
                      help="lens intersections: robust (default) or the paper's cases 1-3 with counted fallbacks")
    run.add_argument("--threads", type=int, default=None, help="CPU threads of the kernel (default: every core)")
    outs = p.add_argument_group("what is written")
    outs.add_argument("--image", metavar="PNG", help="also save the 24-LED flat-gel image")
    add_json_flag(outs)
    p.set_defaults(func=_trace)


def _add_section(group) -> None:
    """``sim section``: the radial section of a scene to a PNG."""
    p = group.add_parser("section", help="draw the radial section of a scene with sample rays to a PNG",
                         description="Draw the radial section (lens profile, LED, gel, sample rays) and the "
                                     "24-LED image, like the paper's Fig. 2.")
    p.add_argument("scene")
    p.add_argument("--out", default=None, help="PNG path (default: <scene>-section.png)")
    p.add_argument("--rays", type=int, default=25, help="rays drawn in the section (default 25)")
    p.add_argument("--no-image", action="store_true", help="only the section, not the 24-LED image")
    add_json_flag(p)
    p.set_defaults(func=_section)


def _add_optimize_lens(group) -> None:
    """``sim optimize-lens``: the lens optimizer's options, grouped by what they set."""
    p = group.add_parser("optimize-lens", help="optimise a scene's lens for flux, uniformity or photometric stereo",
                         description="Optimise the lens of a scene: Nelder-Mead (or CMA-ES) over the lens dimensions "
                                     "(and optionally "
                                     "a conic top and the LED tilt) under manufacturing limits, every candidate "
                                     "traced with the same rays; the winner is confirmed as `sim trace` measures "
                                     "it, its tolerance to +-0.1 mm measured, and written as a scene file. "
                                     "Defaults come from the scene's design section, then from these options.")
    p.add_argument("scene", help="shipped scene name or a YAML path (its lens is the starting design)")
    g = p.add_argument_group("what to optimise")
    g.add_argument("--objective", choices=("flux", "cv", "channel-cv", "valid", "condition"), default=None,
                   help="maximise flux on screen, minimise the 24-LED image's CV, minimise the worst per-channel CV "
                        "of --mode, maximise the fraction of well-conditioned pixels of --mode, or minimise their "
                        "median condition number (default: the scene's, else flux)")
    g.add_argument("--mode", nargs="+", default=None, metavar="MODE",
                   help="lighting modes of the per-channel and photometric-stereo figures (e.g. trichromatic)")
    for flag, help_text in (("--min-flux", "fraction on screen at least"), ("--max-cv", "24-LED image CV at most"),
                            ("--max-channel-cv", "worst per-channel CV of --mode at most"),
                            ("--min-valid", "fraction of well-conditioned pixels of --mode at least"),
                            ("--max-median-condition", "median condition number of --mode at most")):
        g.add_argument(flag, default=None, metavar="X|bare",
                       help=f"constraint: {help_text} (a number, or 'bare': the scene's figure without its lens)")
    g = p.add_argument_group("design space")
    g.add_argument("--vary", nargs="+", default=None, metavar="PARAM",
                   help="parameters to vary: arc_radius centre_rho centre_z top_radius top_conic apex_z bottom_z "
                        "led_tilt_deg (default: the scene's, else the first six)")
    g.add_argument("--bound", nargs=3, action="append", default=None, metavar=("PARAM", "LOW", "HIGH"),
                   help="search bounds of a parameter (mm, deg; varies it too); repeatable")
    g.add_argument("--start", nargs=2, action="append", default=None, metavar=("PARAM", "VALUE"),
                   help="starting value of a parameter (default: the scene's); repeatable")
    for flag, help_text in (("--min-thickness", "centre thickness (default 2)"),
                            ("--min-edge-thickness", "side wall height at the rim (default 1)"),
                            ("--led-clearance", "LED to lens distance (default 0.5)"),
                            ("--housing-radius", "widest lens radius (default: the larger of ring radius + 5 and the gel's half-diagonal)"),
                            ("--gel-gap", "gap between apex and gel (default 1)"),
                            ("--window-radius", "the top (the camera's window) spans at least this radius (default 0)"),
                            ("--tolerance-mm", "the lens must still close with any one dimension this far off "
                                               "(default 0.1)")):
        g.add_argument(flag, type=float, default=None, metavar="MM", help=f"manufacturing limit: {help_text}")
    g = p.add_argument_group("search")
    g.add_argument("--method", choices=("nelder-mead", "cmaes", "random"), default=None,
                   help="optimizer (default nelder-mead, measured best on the shipped briefs; cmaes and random "
                        "search for comparison: iristac bench lens)")
    g.add_argument("--evaluations", type=int, default=None, help="designs to evaluate (default: the scene's, else 600)")
    g.add_argument("--seconds", type=float, default=None, help="stop the search after this wall time")
    g.add_argument("--rays", type=int, default=None, help="rays per candidate (default: the scene's, else 100000)")
    g.add_argument("--sampler", choices=SAMPLERS, default=None, help="ray sampler of the search (default sobol)")
    g.add_argument("--grid", type=int, default=None, help="rows of the coarse screen grid of the search (default 40)")
    g.add_argument("--seed", type=int, default=None, help="seed of the rays and of the optimizer (default 0)")
    g.add_argument("--sigma0", type=float, default=None,
                   help="initial step (simplex size, CMA-ES sigma) as a fraction of each bound (default 0.25)")
    g.add_argument("--popsize", type=int, default=None, help="CMA-ES population (default: cma's, 4 + 3 ln d)")
    g.add_argument("--max-condition", type=float, default=None,
                   help="condition number up to which a pixel counts as well conditioned (default 1000, the solvers')")
    g.add_argument("--region", type=float, default=None,
                   help="active area of the per-channel and photometric-stereo figures: the centred disc of this "
                        "fraction of the screen's smaller side (default: the scene's, else 0.9)")
    g.add_argument("--confirm-rays", type=int, default=None, help="rays of the confirming trace (default 1e6)")
    g.add_argument("--tolerance-rays", type=int, default=None, help="rays per design of the tolerance analysis")
    g.add_argument("--no-tolerance", action="store_true", help="skip the tolerance analysis")
    g = p.add_argument_group("where it runs")
    g.add_argument("--device", default="cpu", help="cpu, or a CUDA device (cuda, cuda:1) (default cpu)")
    g.add_argument("--threads", type=int, default=None, help="CPU threads of every trace (default: the engine's)")
    g.add_argument("--engine", choices=("kernel", "torch"), default=None,
                   help="tracer of every candidate: the compiled kernel (default) or the eager torch reference "
                        "(a conic top needs it)")
    g = p.add_argument_group("what is written")
    g.add_argument("--out", default=None, metavar="DIR",
                   help="folder for the winner's scene file, trajectory.json/png and section drawings")
    g.add_argument("--plot", default=None, metavar="PNG", help="write the trajectory figure here")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_json_flag(g)
    p.set_defaults(func=_optimize)


def _add_synthesize(group) -> None:
    """``sim synthesize``: stage 1, a scene's illumination model through the store."""
    p = group.add_parser("synthesize", help="stage 1: trace a scene into illumination.h5 (cached in the store)",
                         description="Trace every LED onto the camera pixel grid and write the illumination model "
                                     "(per-LED V, per-pattern light matrices) through the stage store.")
    p.add_argument("scene")
    grid = p.add_argument_group("camera grid")
    grid.add_argument("--shape", type=int, nargs=2, metavar=("H", "W"), required=True, help="camera image size")
    grid.add_argument("--mm-per-px", type=float, required=True, help="pixel pitch on the gel (mm)")
    rays = p.add_argument_group("rays")
    run = p.add_argument_group("where it runs")
    _trace_options(rays, run)
    pat = p.add_argument_group("lighting patterns")
    pat.add_argument("--drive", metavar="NPY", help="lighting patterns: a .npy array (P, L, 3) of LED drives")
    pat.add_argument("--brightness", metavar="NPY", help="a .npy array (P,) of pattern brightnesses")
    pat.add_argument("--gains", metavar="NPY", help="a .npy array (L,) or (L, 3) of calibrated LED gains")
    pat.add_argument("--exposure", type=float, default=1.0, help="camera exposure mu of the light matrices")
    outs = p.add_argument_group("what is written")
    outs.add_argument("--out", required=True, help="illumination.h5 to write")
    outs.add_argument("--cache", default=None,
                      help="stage store folder (default $IRISTAC_CACHE or ./iristac-cache)")
    add_json_flag(outs)
    p.set_defaults(func=_synthesize)



def _trace_options(rays, run):
    """The tracing options of ``trace`` and ``synthesize``: the rays to ``rays``, the device,
    precision and engine to ``run`` (argument groups, or the same parser twice)."""
    rays.add_argument("--rays", type=int, default=None, help="rays per traced LED (default: the scene's, 1e6)")
    rays.add_argument("--sampler", choices=SAMPLERS, default=None, help="ray sampler (default: the scene's)")
    rays.add_argument("--seed", type=int, default=None, help="sampler seed (default: the scene's)")
    rays.add_argument("--method", choices=METHODS, default="hits",
                      help="every LED by hit rotation (exact, default), image rotation (the paper's) or tracing each")
    run.add_argument("--device", default="cpu", help="cpu, or a CUDA device (cuda, cuda:1): the kernel on the GPU")
    run.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    run.add_argument("--engine", choices=("kernel", "torch"), default=None,
                     help="the compiled kernel (default; compiles once, then cached on disk) or the eager torch "
                          "reference (the only one for --intersection paper)")


def _device(name: str, engine: str | None = None, intersection: str | None = None) -> str:
    """Check ``--device`` up front: a clear error instead of a traceback from deep in numba or torch."""
    import re

    from sim.optics.engine import resolve_engine

    if not re.fullmatch(r"cpu|cuda(:\d+)?", name):
        raise UserError(f"--device {name!r}: not a device; expected cpu, cuda or cuda:N")
    if not name.startswith("cuda"):
        return name
    try:
        kind = resolve_engine(engine, intersection or "robust")
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if kind == "kernel":
        from sim.optics.kernel_cuda import cuda_available

        ok, why = cuda_available()
    else:
        import torch

        ok, why = torch.cuda.is_available(), "torch sees no CUDA device"
    if not ok:
        raise UserError(f"--device {name!r}: CUDA is not available on this machine ({why}); use --device cpu")
    return name


def _engine(args):
    from sim.optics.engine import resolve_engine

    try:
        return resolve_engine(args.engine, getattr(args, "intersection", None) or "robust")
    except ValueError as exc:
        raise UserError(f"--engine {args.engine}: {exc}") from None


def _check_rays(args):
    if args.rays is not None and args.rays < 1:
        raise UserError(f"--rays must be a positive integer, got {args.rays}")


def _trace(args) -> int:
    from sim.lens_design import TRACE_KEYS, trace_report

    _check_rays(args)
    if args.engine == "kernel" and args.intersection == "paper":
        raise UserError("--engine kernel implements the robust intersection only; use --engine torch with "
                        "--intersection paper")
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be a positive integer, got {args.threads}")
    engine = args.engine
    r = trace_report(args.scene, rays=args.rays, sampler=args.sampler, seed=args.seed, no_lens=args.no_lens,
                     method=args.method, device=_device(args.device, args.engine, args.intersection),
                     dtype=args.dtype, images=bool(args.image), intersection=args.intersection, engine=engine,
                     threads=args.threads)
    if args.image:
        _save_image(r.pop("image"), args.image, f"{r['scene']} ({'lens' if r['lens'] else 'no lens'})")
    out = {k: r[k] for k in TRACE_KEYS}
    if args.json:
        print_json(out)
    else:
        print(f"scene {out['scene']} ({'with' if out['lens'] else 'without'} lens), {out['rays']} rays per traced "
              f"LED ({out['sampler']}, {out['method']}, {out['intersection']} intersections) on {out['device']}, "
              f"{out['engine']} engine, {out['dtype']}")
        print(f"  fraction on screen  {100 * out['fraction_on_screen']:.2f} %")
        print(f"  mean intensity      {out['mean_intensity']:.4g} W/m^2 per W per LED")
        print(f"  uniformity          CV {out['uniformity_cv']:.4f}, min/max {out['min_max']:.4f}")
        for ch, v in out["channels"].items():
            print(f"    {ch}: CV {v['uniformity_cv']:.4f}, min/max {v['min_max']:.4f}")
        print(f"  time                {out['seconds']:.3f} s ({out['rays_per_second'] / 1e6:.2f} M rays/s)"
              + (f", plus {out['compile_seconds']:.2f} s to compile or load the kernel" if out["compile_seconds"] else
                 ""))
        print(f"  energy residual     {out['energy_residual']:.3g}")
        shown = {k: v for k, v in out["counters"].items() if v}
        if shown:
            print("  counters            " + ", ".join(f"{k} {v}" for k, v in sorted(shown.items())))
    return 0


def _save_image(img, path, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4.5))
    im = ax.imshow(img.mean(axis=2) * 1e6, origin="lower", cmap="inferno")
    fig.colorbar(im, ax=ax, label="W/m^2 per W per LED")
    ax.set_title(title)
    from sim.figures import save_figure

    save_figure(fig, path, dpi=100)


def _section(args) -> int:
    from sim.scene import load_scene
    from sim.section import draw_section

    scene = load_scene(args.scene)
    out = args.out or f"{scene.name}-section.png"
    if args.rays < 1:
        raise UserError(f"--rays must be a positive integer, got {args.rays}")
    path = draw_section(scene, out, rays=args.rays, image=not args.no_image)
    if args.json:
        print_json({"out": str(path), "scene": scene.name, "rays": args.rays})
    else:
        print(f"wrote {path}")
    return 0


def _bound_value(flag, v):
    if v is None or v == "bare":
        return v
    try:
        return float(v)
    except ValueError:
        raise UserError(f"{flag}: expected a number or 'bare', got {v!r}") from None


def _optimize(args) -> int:
    import sys

    from sim.lens_design import OPTIMIZE_KEYS, optimize_lens
    from sim.lensopt.space import DEFAULT_BOUNDS, PARAMETERS
    from sim.scene import load_scene

    scene = load_scene(args.scene)
    cons = {k: _bound_value("--" + k.replace("_", "-"), getattr(args, k))
            for k in ("min_flux", "max_cv", "max_channel_cv", "min_valid", "max_median_condition")}
    cons = {k: v for k, v in cons.items() if v is not None}
    vary = None
    if args.vary or args.bound:
        scene_vary = {k: tuple(v) for k, v in ((scene.design or {}).get("vary") or {}).items()}
        names = list(args.vary or scene_vary or [])
        vary = {}
        for k in names:
            if k not in PARAMETERS:
                raise UserError(f"--vary: unknown parameter {k!r}; expected one of {', '.join(PARAMETERS)}")
            vary[k] = scene_vary.get(k, DEFAULT_BOUNDS[k])
        for k, lo, hi in args.bound or []:
            if k not in PARAMETERS:
                raise UserError(f"--bound: unknown parameter {k!r}; expected one of {', '.join(PARAMETERS)}")
            vary[k] = (_float("--bound " + k, lo), _float("--bound " + k, hi))
    start = {k: _float("--start " + k, v) for k, v in (args.start or [])} or None
    manuf = {k: getattr(args, k) for k in ("min_thickness", "min_edge_thickness", "led_clearance", "housing_radius",
                                          "gel_gap", "window_radius") if getattr(args, k) is not None}
    if args.tolerance_mm is not None:
        manuf["tolerance"] = args.tolerance_mm
    if manuf:
        base = dict((scene.design or {}).get("manufacturing") or {})
        manuf = {**base, **manuf}
    r = optimize_lens(scene, objective=args.objective, modes=args.mode, constraints=cons or None, vary=vary,
                      start=start, manufacturing=manuf or None, method=args.method, rays=args.rays,
                      sampler=args.sampler, grid=args.grid, evaluations=args.evaluations, seconds=args.seconds,
                      seed=args.seed, sigma0=args.sigma0, popsize=args.popsize, max_condition=args.max_condition,
                      region=args.region, confirm_rays=args.confirm_rays, tolerance_rays=args.tolerance_rays,
                      tolerance=not args.no_tolerance, out=args.out, plot=args.plot,
                      device=_device(args.device, args.engine), threads=args.threads, engine=args.engine,
                      progress=not args.no_progress,
                      log=lambda m: print(f"[optimize-lens] {m}", file=sys.stderr))
    out = {k: r[k] for k in OPTIMIZE_KEYS}
    if args.json:
        print_json(out)
        return 0
    _print_optimize(out)
    return 0


def _float(flag, v):
    try:
        return float(v)
    except ValueError:
        raise UserError(f"{flag}: expected a number, got {v!r}") from None


def _print_optimize(r) -> None:
    def fig(d):
        s = f"{100 * d['fraction_on_screen']:.2f} % on screen, CV {d['uniformity_cv']:.4f}"
        if d.get("valid_fraction") is not None:
            s += (f", valid {100 * d['valid_fraction']:.1f} %, median condition {d['median_condition']:.3g}, "
                  f"channel CV {d['channel_cv']:.3f}")
        return s

    print(f"scene {r['scene']}: objective {r['objective']}" + (f" ({', '.join(r['modes'])})" if r["modes"] else "")
          + f", constraints {r['constraints'] or 'none'}; {r['method']} over {', '.join(r['varied'])}")
    print(f"  {r['evaluations']} designs ({r['traced']} traced) in {r['seconds']:.1f} s; confirmed with "
          f"{r['confirm_rays']:,} rays")
    ref = r["bare"].get("reference") or {}
    print(f"  bare LEDs  {fig(r['bare'])}" + (f"  ({', '.join(f'{k} {v:g}' for k, v in ref.items())})" if ref else ""))
    print(f"  start      {fig(r['start'])}")
    print(f"  optimized  {fig(r)}" + ("" if r["feasible"] else "  (NO FEASIBLE DESIGN FOUND: best infeasible shown)"))
    print(f"  lens off   {fig(r['lens_off'])}  (the optimized LEDs without the lens)")
    print("  design     " + ", ".join(f"{k} {v:.4g}" for k, v in r["design"].items()))
    tol = r.get("tolerance")
    if tol:
        print(f"  tolerance (+-{tol['delta_mm']} mm, {tol['rays']:,} rays): worst |d flux| "
              f"{100 * (tol['worst_d_flux'] or 0):.3f} points, worst |d CV| {tol['worst_d_cv'] or 0:.4f}")
        for row in tol["rows"]:
            if row["d_flux_max"] is None:
                print(f"    {row['parameter']:<13} {row['note']}")
                continue
            print(f"    {row['parameter']:<13} |d flux| {100 * row['d_flux_max']:.3f} points, |d CV| "
                  f"{row['d_cv_max']:.4f}" + (f"  ({row['note'].strip()})" if row["note"] else ""))
    for k, v in r["files"].items():
        print(f"  {k}: {v}")


def _load_npy(path, name):
    import numpy as np

    if path is None:
        return None
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise UserError(f"--{name} {path}: cannot read a .npy array ({exc})") from None


def _synthesize(args) -> int:
    import time

    from pipeline.base.store import StageStore
    from pipeline.stages import synthesize as synthesize_stage
    from sim.synthesize import save_illumination

    _check_rays(args)
    t0 = time.perf_counter()
    store = StageStore(args.cache) if args.cache else StageStore()
    model, key, cached = synthesize_stage.run(
        store, args.scene, tuple(args.shape), args.mm_per_px, drive=_load_npy(args.drive, "drive"),
        brightness=_load_npy(args.brightness, "brightness"), gains=_load_npy(args.gains, "gains"),
        exposure=args.exposure, rays=args.rays, sampler=args.sampler, seed=args.seed, method=args.method,
        device=_device(args.device, args.engine), dtype=args.dtype, engine=_engine(args))
    path = save_illumination(model, args.out)
    res = {"out": str(path), "key": key.digest, "cached": cached, "shape": list(model.shape),
           "leds": model.num_leds, "mm_per_px": model.mm_per_px, "seconds": time.perf_counter() - t0,
           "patterns": int(model.meta["light_matrices"].shape[0]) if "light_matrices" in model.meta else 0}
    if args.json:
        print_json(res)
    else:
        print(f"wrote {path} ({res['leds']} LEDs, {res['shape'][0]}x{res['shape'][1]} px, "
              f"{res['patterns']} patterns; {'from cache' if cached else 'traced'} in {res['seconds']:.2f} s)")
    return 0
