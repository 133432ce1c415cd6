"""``iristac bench reconstruct``: time and error of every normal solver and depth integrator.

Scene: a 3 mm ball pressed 0.5 mm into the gel, seen over a 16 x 12 mm field at each image
size, lit by 8 white sectors of the bare 24-LED ring 30 mm below the gel (closed-form
near-field light, :mod:`pipeline.bench.recon_scene`), rendered with per-channel albedo,
Gaussian noise sigma = 1 DN and 8-bit quantisation. The solvers see uint8 frames
``(P, H, W, 3)`` and the exact light model (per-pixel for near-field, the centre pixel's
vectors for far-field); timings are per frame with the light model prepared once, the best of
``--repeats`` runs (the CPU is shared), torch and BLAS (the numpy far-field solver's products)
on ``--threads`` threads.

The real-time pipelines (far-field least squares + DST or FC, uint8 frames to heights) are
timed with the eager solver and with the ``torch.compile``-d one
(:mod:`pipeline.normals.fused`); the issue's targets are >= 200 fps at 320 x 240 and >= 60
fps at 640 x 480 on the 2-core CPU, and the table prints them beside the measurement.

Robust vs least squares: per pixel, a random fifth of the observations is corrupted, either
clipped (half set to 0 = shadow, half to 255 = saturated) or partially shadowed (scaled by
0.25, above the dark threshold, so only the reweighting can reject it).

The photometric-stereo section (objects with highlights and cast shadows under 96 far-field
lights, masked vs bounding box, ``reconstruct`` end to end) is
:mod:`pipeline.bench.reconstruct_ps`; ``--sections`` picks what runs.
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.bench.recon_scene import render_sphere_scene

FOV_MM = 16.0
#: Frame-rate targets of the real-time pipeline (issue: normals and depth).
TARGET_FPS = {"320x240": 200.0, "640x480": 60.0}
RADIUS, DEPTH = 3.0, 0.5
PATTERNS = 8


def add_arguments(parser) -> None:
    parser.add_argument("--sizes", nargs="*", default=None, metavar="WxH",
                        help="image sizes (default 320x240 640x480; --quick: 160x120)")
    parser.add_argument("--repeats", type=int, default=None, help="timing repeats (best is kept)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op and BLAS threads")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--no-compile", action="store_true",
                        help="skip the torch.compile-d far-field solver (no C++ compiler, or to save its warm-up)")
    parser.add_argument("--sections", nargs="+", choices=["tactile", "ps"], default=["tactile", "ps"],
                        help="tactile: the sensor scene at --sizes; ps: objects under 96 far-field lights")
    parser.add_argument("--ps-radius", type=float, default=None,
                        help="PS object radius in pixels (default 71: 15.8k pixels; --quick: 20)")


def _best(fn, repeats: int) -> tuple[float, float, list[float], object]:
    """``(best wall time, best process CPU time, every run's wall time, result)`` of ``repeats``
    runs (with one torch thread, CPU time is what a frame costs when it has a core to itself:
    the shared machine's wall times include waiting for one)."""
    best_cpu, out, times = float("inf"), None, []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        best_cpu = min(best_cpu, time.process_time() - c)
        times.append(time.perf_counter() - t)
    return min(times), best_cpu, times, out


def _obs(frames: np.ndarray) -> np.ndarray:
    P, H, W, C = frames.shape
    return frames.transpose(0, 3, 1, 2).reshape(P * C, H, W)


def _corrupt(frames: np.ndarray, kind: str, rng) -> np.ndarray:
    obs = _obs(frames).astype(np.float32)
    N = obs.shape[0]
    # A fifth of the observations at every pixel, chosen independently per pixel.
    pick = np.argsort(rng.random(obs.shape), axis=0) < max(1, N // 5)
    if kind == "clipped":
        value = np.where(rng.random(obs.shape) < 0.5, 0.0, 255.0)
        obs = np.where(pick, value, obs)
    else:
        obs = np.where(pick, np.round(obs * 0.25), obs)
    return obs


def measure_size(width: int, height: int, repeats: int, device: str, no_compile: bool = False) -> dict:
    """All measurements at one image size."""
    from pipeline.depth import integrate
    from pipeline.normals import FarFieldSolver, NearFieldSolver, ratio_to_reference, solve_cauchy, solve_robust_irls
    from pipeline.results.evaluate import normal_error_stats

    mm = FOV_MM / width
    s = render_sphere_scene((height, width), mm, radius=RADIUS, depth=DEPTH, num_patterns=PATTERNS, noise=1.0,
                            bits=8, seed=0)
    frames = s.frames.astype(np.uint8)
    groups = np.tile(np.arange(3), PATTERNS)
    out: dict = {"size": f"{width}x{height}", "mm_per_px": mm, "solvers": {}, "integrators": {}, "robust": {}}

    def err(res):
        return normal_error_stats(res.normals, s.normals)["mean_deg"]

    far = FarFieldSolver(s.lights_far(), groups=groups, device=device)
    # The real-time path: the same solve as one torch.compile-d loop (pipeline.normals.fused);
    # its first frame compiles (timed separately, then excluded like any warm-up).
    fast = FarFieldSolver(s.lights_far(), groups=groups, device=device, compile=not no_compile)
    t0 = time.perf_counter()
    fast.solve_frames(frames)
    out["compile_seconds"] = time.perf_counter() - t0 if fast.compile else None
    near = NearFieldSolver(s.lights_flat(), groups=groups, device=device)
    solvers = {
        "lstsq (far field)": lambda: far.solve_frames(frames),
        "lstsq (far field, compiled)": lambda: fast.solve_frames(frames),
        "nearfield": lambda: near.solve(_obs(frames)),
        "robust (near field)": lambda: solve_robust_irls(_obs(frames), s.lights_flat(), groups=groups,
                                                         dark_threshold=2.55, saturation=255.0, device=device),
        "cauchy (near field)": lambda: solve_cauchy(_obs(frames), s.lights_flat(), groups=groups, dark_threshold=2.55,
                                                    saturation=255.0, device=device),
    }
    ref_obs = _obs(s.reference.astype(np.uint8)).astype(np.float32)
    solvers["nearfield + ratio"] = lambda: near_ratio()

    def near_ratio():
        r, Lr = ratio_to_reference(_obs(frames), ref_obs, s.lights_flat())
        return NearFieldSolver(Lr, device=device).solve(r)

    results = {}
    for name, fn in solvers.items():
        if name.endswith("compiled)") and not fast.compile:
            continue  # compilation unavailable or skipped: nothing to report
        reps = repeats if name.startswith(("lstsq", "nearfield")) and "ratio" not in name else max(1, repeats // 5)
        sec, cpu, runs, res = _best(fn, reps)
        results[name] = res
        out["solvers"][name] = {"seconds": sec, "fps": 1.0 / sec, "cpu_seconds": cpu, "seconds_runs": runs,
                                "mean_deg": err(res), "valid_fraction": res.valid_fraction}
    from pipeline.base.registry import INTEGRATORS

    for method in INTEGRATORS.names():  # every registered integrator
        for src in ("nearfield", "lstsq (far field)"):
            res = results[src]
            reps = repeats if method != "sparse" else max(1, repeats // 10)
            sec, cpu, runs, d = _best(lambda: integrate(res.normals, mm, res.mask, method=method), reps)
            rmse = float(np.sqrt(np.mean((d.height.astype(np.float64) - s.height) ** 2)))
            out["integrators"].setdefault(method, {})[src] = {"seconds": sec, "cpu_seconds": cpu,
                                                            "seconds_runs": runs,
                                                            "rmse_mm": rmse,
                                                            "rmse_pct_depth": 100 * rmse / DEPTH}
    # Real-time pipelines: far-field least squares + DST or FC, from uint8 frames to heights,
    # with the eager and the compiled solver.
    out["pipelines"] = {}
    for solver_name, solver in (("eager", far), ("compiled", fast)):
        if solver_name == "compiled" and not fast.compile:
            continue
        for method in ("dst", "fc"):
            def pipeline(method=method, solver=solver):
                r = solver.solve_frames(frames)
                return integrate(r.normals, mm, r.mask, method=method)
            sec, cpu, runs, _ = _best(pipeline, repeats)
            out["pipelines"][f"lstsq+{method} ({solver_name})"] = {"seconds": sec, "fps": 1.0 / sec,
                                                                   "seconds_runs": runs,
                                                                   "cpu_seconds": cpu, "cpu_fps": 1.0 / cpu,
                                                                   "integrator": method}
    rng = np.random.default_rng(1)
    for kind in ("clipped", "partial shadow"):
        obs = _corrupt(frames, kind, rng)
        ls = near.solve(obs)
        rb = solve_cauchy(obs, s.lights_flat(), groups=groups, dark_threshold=2.55, saturation=255.0, device=device)
        rt = solve_cauchy(obs, s.lights_flat(), groups=groups, dark_threshold=2.55, saturation=255.0, method="trim",
                          device=device)
        rn = solve_robust_irls(obs, s.lights_flat(), groups=groups, dark_threshold=2.55, saturation=255.0,
                               device=device)
        out["robust"][kind] = {"lstsq_deg": err(ls), "robust_deg": err(rn), "robust_irls_deg": err(rb),
                               "robust_trim_deg": err(rt)}
    return out


def run(args) -> dict:
    from pipeline.base.threads import limit_threads

    sizes = getattr(args, "sizes", None) or (["160x120"] if getattr(args, "quick", False) else ["320x240", "640x480"])
    repeats = getattr(args, "repeats", None) or (3 if getattr(args, "quick", False) else 20)
    device = getattr(args, "device", "cpu")
    sections = getattr(args, "sections", None) or ["tactile", "ps"]
    quick = getattr(args, "quick", False)
    per_size, ps = [], None
    threads = getattr(args, "threads", 1)
    with limit_threads(torch=threads, blas=threads):
        for spec in (sizes if "tactile" in sections else []):
            w, h = (int(v) for v in spec.lower().split("x"))
            per_size.append(measure_size(w, h, repeats, device, getattr(args, "no_compile", False)))
        if "ps" in sections:
            from pipeline.bench.reconstruct_ps import measure_ps

            radius = getattr(args, "ps_radius", None) or (20.0 if quick else 71.0)
            ps = measure_ps(radius, (4, 6) if quick else (8, 12), (128, 160) if quick else (512, 612),
                            repeats=min(repeats, 5), device=device)
    rows = []
    solver, integrator = _reconstruct_defaults()
    for r in per_size:
        for name, v in r["solvers"].items():
            rows.append({"knob": f"normal solver @ {r['size']}", "setting": name, "error": v["mean_deg"],
                         "error_unit": "deg", "seconds": v["seconds"], "seconds_runs": v.get("seconds_runs"),
                         "solver": SOLVER_NAMES.get(name, name), "size": r["size"],
                         **({"path": "compiled" if "compiled" in name else "eager"} if name.startswith("lstsq") else {}),
                         "default": name == "lstsq (far field)" and solver == "lstsq"})
        for method, by_src in r["integrators"].items():
            v = by_src["nearfield"]
            rows.append({"knob": f"integrator (near-field normals) @ {r['size']}", "setting": method,
                         "error": v["rmse_mm"], "error_unit": "mm", "seconds": v["seconds"], "size": r["size"],
                         "seconds_runs": v.get("seconds_runs"), "default": method == integrator})
        for key, v in r["pipelines"].items():
            rows.append({"knob": f"real-time lstsq + depth @ {r['size']}", "setting": key,
                         "error": r["integrators"][v["integrator"]]["lstsq (far field)"]["rmse_mm"], "error_unit": "mm",
                         "seconds": v["seconds"], "seconds_runs": v.get("seconds_runs"), "size": r["size"],
                         "path": "compiled" if "compiled" in key else "eager"})
    if ps is not None:
        from pipeline.bench.reconstruct_ps import ps_rows

        rows += ps_rows(ps)
    return {"scene": {"fov_mm": FOV_MM, "ball_radius_mm": RADIUS, "indentation_mm": DEPTH, "patterns": PATTERNS,
                      "noise_dn": 1.0, "bits": 8},
            "repeats": repeats, "threads": getattr(args, "threads", 1), "device": device, "sizes": per_size,
            "ps": ps, "rows": rows}


#: Registry name of each solver row (its setting names the light model too).
SOLVER_NAMES = {"lstsq (far field)": "lstsq", "lstsq (far field, compiled)": "lstsq", "nearfield": "nearfield",
                "robust (near field)": "robust", "cauchy (near field)": "cauchy", "nearfield + ratio": "nearfield"}


def _reconstruct_defaults() -> tuple[str, str]:
    """``iristac reconstruct``'s default solver and integrator, read from its command line."""
    from pipeline.cli import command_defaults

    a = command_defaults("reconstruct", "CAPTURE.h5", "--out", "OUT")
    return a.solver, a.integrator


def format_table(result: dict) -> str:
    lines = [f"reconstruct: sphere R={RADIUS} mm pressed {DEPTH} mm, {PATTERNS} sector patterns x RGB, 8-bit, "
             f"sigma 1 DN; best of {result['repeats']} runs, {result['threads']} torch/BLAS thread(s), {result['device']}"]
    for r in result["sizes"]:
        lines.append(f"\n== {r['size']} ({r['mm_per_px']:.4f} mm/px)")
        lines.append(f"{'solver':<30}{'wall ms':>9}{'fps':>9}{'cpu ms':>9}{'mean err deg':>14}{'valid':>8}")
        for name, v in r["solvers"].items():
            lines.append(f"{name:<30}{v['seconds'] * 1e3:9.2f}{v['fps']:9.1f}{v['cpu_seconds'] * 1e3:9.2f}"
                         f"{v['mean_deg']:14.3f}{v['valid_fraction']:8.3f}")
        lines.append(f"{'integrator':<12}{'wall ms':>9}{'cpu ms':>9}{'RMSE um (near)':>16}{'% depth':>9}"
                     f"{'RMSE um (far)':>15}")
        for method, by_src in r["integrators"].items():
            n, f = by_src["nearfield"], by_src["lstsq (far field)"]
            lines.append(f"{method:<12}{n['seconds'] * 1e3:9.2f}{n['cpu_seconds'] * 1e3:9.2f}{n['rmse_mm'] * 1e3:16.2f}"
                         f"{n['rmse_pct_depth']:9.2f}{f['rmse_mm'] * 1e3:15.1f}")
        for key, v in r["pipelines"].items():
            lines.append(f"{key} pipeline (uint8 frames -> heights): wall {v['seconds'] * 1e3:.2f} ms = "
                         f"{v['fps']:.1f} fps; cpu {v['cpu_seconds'] * 1e3:.2f} ms = {v['cpu_fps']:.1f} fps")
        if r["size"] in TARGET_FPS and r["pipelines"]:
            best_key = max(r["pipelines"], key=lambda k: r["pipelines"][k]["fps"])
            fps = r["pipelines"][best_key]["fps"]
            verdict = "met" if fps >= TARGET_FPS[r["size"]] else "NOT met"
            lines.append(f"target >= {TARGET_FPS[r['size']]:.0f} fps at {r['size']}: {verdict} "
                         f"({best_key}: {fps:.1f} fps wall)")
        if r.get("compile_seconds") is not None:
            lines.append(f"(compiled solver: first frame at this size took {r['compile_seconds']:.1f} s, "
                         f"compilation included; excluded from the timings above)")
        for kind, v in r["robust"].items():
            lines.append(f"a fifth of observations {kind}: lstsq {v['lstsq_deg']:.3f} deg, robust "
                         f"{v['robust_deg']:.3f} deg, cauchy {v['robust_irls_deg']:.3f} deg, trimmed "
                         f"{v['robust_trim_deg']:.3f} deg")
    if result.get("ps"):
        from pipeline.bench.reconstruct_ps import format_ps

        lines.append(format_ps(result["ps"]))
    return "\n".join(lines)
