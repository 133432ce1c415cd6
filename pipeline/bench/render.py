"""``iristac bench render``: renderer frames per second per effect set and image size.

Every row renders a sphere press under the 24-LED colour-wheel pattern (all 24 LEDs lit) on
the bare-LED ring model:

``cached``
    the per-LED shading of the surface is computed once (:meth:`sim.render.Renderer.set_surface`)
    and only the frame is rendered: the virtual camera's case (the scene changes far less
    often than the LEDs);
``full``
    the surface's shading is recomputed for every frame as well (a scene that moves every
    frame, and every surface effect such as cast shadows paid per frame).

``error`` is the largest difference (DN) between the float32 frame and a float64 render of
the same noiseless scene: what single precision costs in accuracy. The cast-shadow step rows
compare shadow masks with a 0.25-pixel-step reference (fraction of LED-pixel pairs that
differ).
"""

from __future__ import annotations

import time

import numpy as np

EFFECT_SETS = {
    "none": dict(attached_shadows=False),
    "basic": dict(read_noise=1.0, shot_noise=0.1, bit_depth=8),
    "camera": dict(read_noise=1.0, shot_noise=0.1, bit_depth=8, saturation=True, dark_level=4.0, vignetting=0.3,
                   crosstalk=[[0.92, 0.06, 0.02], [0.05, 0.9, 0.05], [0.02, 0.08, 0.9]], distortion=(0.05, 0.0)),
    "depth": dict(read_noise=1.0, shot_noise=0.1, bit_depth=8, depth_field=True),
    "cast": dict(read_noise=1.0, shot_noise=0.1, bit_depth=8, cast_shadows=True),
}


def add_arguments(parser) -> None:
    parser.add_argument("--device", default="cpu", help="torch device (cpu or cuda)")
    parser.add_argument("--seconds", type=float, default=1.0, help="time budget per measurement")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (default 1: on a shared 2-core machine more threads spin-wait "
                             "and make frame times erratic)")


def _rate(fn, budget: float, min_reps: int = 3) -> float:
    """Seconds per call of ``fn`` (median of repeated timings within ``budget``)."""
    fn()  # warm-up
    times = []
    t_end = time.perf_counter() + budget
    while len(times) < min_reps or time.perf_counter() < t_end:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        if len(times) >= 200:
            break
    return float(np.median(times))


def run(args) -> dict:
    from pipeline.base.threads import limit_threads

    threads = int(getattr(args, "threads", 1) or 1)
    with limit_threads(torch=threads):
        return _run(args, threads)


def _run(args, threads: int) -> dict:
    import torch

    from pipeline.base.modes import mode_brightness, mode_drive
    from sim.geometry import sphere
    from sim.render import Renderer, RenderSettings, auto_exposure, bare_ring_illumination

    quick = bool(getattr(args, "quick", False))
    device = getattr(args, "device", "cpu")
    budget = float(getattr(args, "seconds", 1.0))
    budget = min(budget, 0.3) if quick else budget
    sizes = [(60, 80), (120, 160)] if quick else [(240, 320), (480, 640)]
    drive, bright = mode_drive("multicolour"), mode_brightness("multicolour")
    rows = []
    for h, w in sizes:
        px = 20.0 / w  # a 20 mm wide gel at every size
        heights = np.linspace(0.0, 1.0, 5)
        model = bare_ring_illumination((h, w), px, depth_heights=heights)
        surf = sphere((h, w), px, 2.5, 0.8, center=(1.0, 0.5))
        mu = auto_exposure(model, drive, bright, target_dn=200.0)
        for name, fx in EFFECT_SETS.items():
            s = RenderSettings(exposure=mu, **fx)
            r = Renderer(model, s, device=device)
            r.set_surface(surf)
            cached = _rate(lambda: r.render(drive, bright), budget)

            def full():
                r.set_surface(surf)
                return r.render(drive, bright)

            per_full = _rate(full, budget)
            clean = dict(fx, read_noise=0.0, shot_noise=0.0, bit_depth=None)
            ref = Renderer(model, RenderSettings(exposure=mu, **clean), device=device, dtype=torch.float64)
            ref.set_surface(surf)
            r32 = Renderer(model, RenderSettings(exposure=mu, **clean), device=device)
            r32.set_surface(surf)
            err = float(np.abs(r32.render(drive, bright).astype(np.float64) - ref.render(drive, bright)).max())
            effects = ",".join(s.effects) or "none"
            for mode_name, sec in (("cached", cached), ("full", per_full)):
                rows.append({"knob": f"render {w}x{h} ({mode_name})", "setting": name, "seconds": sec,
                             "fps": 1.0 / sec, "error": err, "error_unit": "DN (float32 vs float64)",
                             "effects": effects, "size": f"{w}x{h}", "surface": mode_name, "device": device})
    # cast-shadow marching step: accuracy against time
    h, w = sizes[0]
    px = 20.0 / w
    model = bare_ring_illumination((h, w), px)
    surf = sphere((h, w), px, 2.5, 1.5, center=(1.0, 0.5))
    ref = Renderer(model, RenderSettings(cast_shadows=True, cast_shadow_step_px=0.25), device=device)
    vis_ref = ref._cast_visibility(surf)
    for step in (0.5, 1.0, 2.0, 4.0):
        r = Renderer(model, RenderSettings(cast_shadows=True, cast_shadow_step_px=step), device=device)
        sec = _rate(lambda: r._cast_visibility(surf), budget)
        err = float((r._cast_visibility(surf) != vis_ref).double().mean())
        rows.append({"knob": f"cast-shadow step {w}x{h}", "setting": f"{step} px", "seconds": sec, "fps": 1.0 / sec,
                     "error": err, "error_unit": "fraction of LED-pixel shadows wrong", "effects": "cast_shadows",
                     "size": f"{w}x{h}", "surface": "visibility only", "device": device})
    return {"device": device, "threads": threads, "pattern": "multicolour (24 LEDs lit)",
            "rows": rows}


def format_table(result: dict) -> str:
    lines = [f"renderer, device {result['device']} ({result['threads']} torch threads), pattern {result['pattern']}",
             f"{'size':<8} {'surface':<15} {'effect set':<10} {'fps':>9} {'ms/frame':>9} {'error':>10}  unit / effects"]
    for r in result["rows"]:
        lines.append(f"{r['size']:<8} {r['surface']:<15} {r['setting']:<10} {r['fps']:>9.1f} {1e3 * r['seconds']:>9.2f} "
                     f"{r['error']:>10.3g}  {r['error_unit']}; {r['effects']}")
    return "\n".join(lines)
