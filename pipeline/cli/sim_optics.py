"""``iristac sim trace|section|optimize-lens|synthesize``: the ray tracer's commands.

Each command parses its options and calls one documented function:
``trace`` -> :func:`sim.lens_design.trace_report`, ``section`` -> :func:`sim.section.draw_section`,
``optimize-lens`` -> :func:`sim.lens_design.optimize_lens`, ``synthesize`` ->
:func:`pipeline.stages.synthesize.synthesize_to_store`.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.cli._common import add_json_flag, print_json
from pipeline.base.errors import UserError

SAMPLERS = ("grid", "random", "stratified", "sobol")
METHODS = ("hits", "image", "trace")


def register(group):
    p = group.add_parser("trace", help="trace a scene and report flux on screen and uniformity",
                         description="Trace every LED of a scene onto its imaging plane; print the fraction of "
                                     "light on screen, mean intensity and uniformity (the paper's figures).")
    p.add_argument("scene", help="shipped scene name (default, plano-sphere) or a YAML path")
    _trace_options(p)
    p.add_argument("--no-lens", action="store_true", help="trace without the lens (the paper's comparison)")
    p.add_argument("--intersection", choices=("robust", "paper"), default=None,
                   help="lens intersections: robust (default) or the paper's cases 1-3 with counted fallbacks")
    p.add_argument("--image", metavar="PNG", help="also save the 24-LED flat-gel image")
    p.add_argument("--threads", type=int, default=None, help="CPU threads of the kernel (default: every core)")
    add_json_flag(p)
    p.set_defaults(func=_trace)

    p = group.add_parser("section", help="draw the radial section of a scene with sample rays to a PNG",
                         description="Draw the radial section (lens profile, LED, gel, sample rays) and the "
                                     "24-LED image, like the paper's Fig. 2.")
    p.add_argument("scene")
    p.add_argument("--out", default=None, help="PNG path (default: <scene>-section.png)")
    p.add_argument("--rays", type=int, default=25, help="rays drawn in the section (default 25)")
    p.add_argument("--no-image", action="store_true", help="only the section, not the 24-LED image")
    add_json_flag(p)
    p.set_defaults(func=_section)

    p = group.add_parser("optimize-lens", help="search lens shapes for flux on screen under a uniformity constraint",
                         description="Grid search (with one refinement) over side-arc radius and centre and top "
                                     "radius for the largest flux on screen whose image CV stays under --max-cv.")
    p.add_argument("scene")
    for name, lo, hi in (("arc-radius", 10.0, 16.0), ("centre-rho", 24.0, 32.0), ("centre-z", 6.0, 14.0),
                         ("top-radius", 200.0, 1000.0)):
        p.add_argument(f"--{name}", type=float, nargs=2, metavar=("LOW", "HIGH"), default=(lo, hi),
                       help=f"search bounds in mm (default {lo} {hi})")
    p.add_argument("--steps", type=int, default=3, help="grid points per parameter (default 3)")
    p.add_argument("--refine", type=int, default=1, help="refinement rounds around the best (default 1)")
    p.add_argument("--max-cv", type=float, default=0.5, help="uniformity constraint on the image CV (default 0.5)")
    p.add_argument("--rays", type=int, default=20_000, help="rays per candidate (default 20000)")
    p.add_argument("--out-dir", default="optimize-lens", help="folder for the before/after images")
    p.add_argument("--device", default="cpu")
    p.add_argument("--engine", choices=("kernel", "torch"), default=None,
                   help="tracer of every candidate: the compiled kernel (default) or the eager torch reference")
    add_json_flag(p)
    p.set_defaults(func=_optimize)

    p = group.add_parser("synthesize", help="stage 2: trace a scene into illumination.h5 (cached in the store)",
                         description="Trace every LED onto the camera pixel grid and write the illumination model "
                                     "(per-LED V, per-pattern light matrices) through the stage store.")
    p.add_argument("scene")
    p.add_argument("--shape", type=int, nargs=2, metavar=("H", "W"), required=True, help="camera image size")
    p.add_argument("--mm-per-px", type=float, required=True, help="pixel pitch on the gel (mm)")
    p.add_argument("--out", required=True, help="illumination.h5 to write")
    _trace_options(p)
    p.add_argument("--drive", metavar="NPY", help="lighting patterns: a .npy array (P, L, 3) of LED drives")
    p.add_argument("--brightness", metavar="NPY", help="a .npy array (P,) of pattern brightnesses")
    p.add_argument("--gains", metavar="NPY", help="a .npy array (L,) or (L, 3) of calibrated LED gains")
    p.add_argument("--exposure", type=float, default=1.0, help="camera exposure mu of the light matrices")
    p.add_argument("--cache", default=None, help="stage store folder (default $IRISTAC_CACHE or ./iristac-cache)")
    add_json_flag(p)
    p.set_defaults(func=_synthesize)


def _trace_options(p):
    p.add_argument("--rays", type=int, default=None, help="rays per traced LED (default: the scene's, 1e6)")
    p.add_argument("--sampler", choices=SAMPLERS, default=None, help="ray sampler (default: the scene's)")
    p.add_argument("--seed", type=int, default=None, help="sampler seed (default: the scene's)")
    p.add_argument("--method", choices=METHODS, default="hits",
                   help="every LED by hit rotation (exact, default), image rotation (the paper's) or tracing each")
    p.add_argument("--device", default="cpu", help="cpu, or a CUDA device (cuda, cuda:1): the kernel on the GPU")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--engine", choices=("kernel", "torch"), default=None,
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
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


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


def _optimize(args) -> int:
    from dataclasses import asdict

    from sim.lens_design import optimize_lens, trace_report

    if args.steps < 1 or args.rays < 1:
        raise UserError(f"--steps and --rays must be positive, got {args.steps} and {args.rays}")
    r = optimize_lens(args.scene, arc_radius=tuple(args.arc_radius), centre_rho=tuple(args.centre_rho),
                      centre_z=tuple(args.centre_z), top_radius=tuple(args.top_radius), steps=args.steps,
                      max_cv=args.max_cv, rays=args.rays, refine=args.refine,
                      device=_device(args.device, args.engine), engine=_engine(args))
    out_dir = Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    images = {}
    for tag, scene in (("before", r["start_scene"]), ("after", r["scene"])):
        rep = trace_report(scene, rays=args.rays, sampler="sobol", images=True, engine=_engine(args))
        path = out_dir / f"{tag}.png"
        _save_image(rep.pop("image"), path, f"{tag}: {100 * rep['fraction_on_screen']:.1f}% on screen, "
                                            f"CV {rep['uniformity_cv']:.2f}")
        images[tag] = str(path)
    res = {"best": asdict(r["best"]), "start": asdict(r["start"]), "evaluated": r["evaluated"],
           "invalid": r["invalid"], "max_cv": args.max_cv, "images": images}
    if args.json:
        print_json(res)
    else:
        b, s = r["best"], r["start"]
        print(f"evaluated {r['evaluated']} designs ({r['invalid']} invalid geometries skipped)")
        for tag, c in (("start", s), ("best", b)):
            print(f"  {tag:5s} arc radius {c.arc_radius:.3f}, centre (rho {c.centre_rho:.3f}, z {c.centre_z:.3f}), "
                  f"top radius {c.top_radius:.1f}: {100 * c.fraction_on_screen:.2f} % on screen, "
                  f"CV {c.uniformity_cv:.3f}")
        print(f"  images: {images['before']}, {images['after']}")
    return 0


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
    from pipeline.stages.synthesize import synthesize_to_store
    from sim.synthesize import save_illumination

    _check_rays(args)
    t0 = time.perf_counter()
    store = StageStore(args.cache) if args.cache else StageStore()
    model, key, cached = synthesize_to_store(
        args.scene, tuple(args.shape), args.mm_per_px, store, drive=_load_npy(args.drive, "drive"),
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
