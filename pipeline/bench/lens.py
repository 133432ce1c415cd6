"""``iristac bench lens``: the lens optimizer against its targets, and against other optimizers.

Sections (``--only``):

``targets``
    ``optimize-lens paper`` and ``optimize-lens default`` with their scenes' design briefs, as a
    user runs them: the winner's figures as ``sim trace`` measures them against the lens
    targets (paper: >= 78 % on screen with 24-LED CV <= 0.25; default: more flux and a lower CV
    than the bare LEDs, >= 90 % well-conditioned pixels for the photometric-stereo modes), with
    the search's wall time.
``methods``
    the ``paper`` and ``default-v1`` scenes' briefs searched by CMA-ES, uniform random search and
    Nelder-Mead with the same budget of evaluations and the same rays (common random numbers),
    each from two seeds (Nelder-Mead, deterministic, from the start and from a jittered start):
    the best feasible objective found and the time.
``smoothness``
    finite-difference derivatives of the flux and the CV with respect to each dimension of the
    paper winner at steps of 0.001 to 1 mm (same rays for every design): a gradient method sees
    the spread of these numbers.
"""

from __future__ import annotations

import time

SECTIONS = ("targets", "methods", "smoothness")


def add_arguments(parser) -> None:
    parser.add_argument("--only", nargs="*", choices=SECTIONS, help="run only these sections")
    parser.add_argument("--evaluations", type=int, default=600, help="budget per search in the methods section")
    parser.add_argument("--seeds", type=int, default=2, help="seeds per method in the methods section (default 2)")
    parser.add_argument("--methods", nargs="*", default=None, help="methods compared (default: all of them)")
    parser.add_argument("--sigma0", type=float, default=None, help="initial step (default: each brief's)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--plot", default=None,
                        help="write the methods' trajectories to PNGs named after this one (_paper, _default-v1)")


def run(args) -> dict:
    import os

    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(int(getattr(args, "threads", 1) or 1))
    try:
        only = getattr(args, "only", None) or SECTIONS
        out = {"load_average_start": list(os.getloadavg()), "rows": []}
        if "targets" in only:
            out["targets"] = _targets(out["rows"])
        if "methods" in only:
            out["methods"] = _methods(out["rows"], int(getattr(args, "evaluations", 600)), getattr(args, "plot", None),
                                      int(getattr(args, "seeds", 2) or 2), getattr(args, "methods", None),
                                      getattr(args, "sigma0", None))
        if "smoothness" in only:
            out["smoothness"] = _smoothness()
        out["load_average_end"] = list(os.getloadavg())
        return out
    finally:
        torch.set_num_threads(previous)


def _targets(rows) -> dict:
    from sim.lens_design import optimize_lens

    res = {}
    for scene in ("paper", "default"):
        r = optimize_lens(scene, tolerance=False, progress=False)
        bare = r["bare"]
        if scene == "paper":
            met = r["fraction_on_screen"] >= 0.78 and r["uniformity_cv"] <= 0.25
            target = "flux >= 78 %, CV <= 0.25"
        else:
            met = (r["fraction_on_screen"] > bare["fraction_on_screen"] and r["uniformity_cv"] < bare["uniformity_cv"]
                   and (r["valid_fraction"] or 0) >= 0.9)
            target = "flux and CV better than bare, valid >= 90 %"
        res[scene] = {"target": target, "met": bool(met), "fraction_on_screen": r["fraction_on_screen"],
                      "uniformity_cv": r["uniformity_cv"], "valid_fraction": r["valid_fraction"],
                      "median_condition": r["median_condition"], "bare_fraction_on_screen": bare["fraction_on_screen"],
                      "bare_uniformity_cv": bare["uniformity_cv"], "evaluations": r["evaluations"],
                      "seconds": r["seconds"], "design": r["design"]}
        rows.append({"knob": f"optimize-lens {scene}", "setting": "scene brief", "error": 1.0 - r["fraction_on_screen"],
                     "error_unit": "fraction off screen", "seconds": r["seconds"]})
    return res


def _methods(rows, evaluations: int, plot, seeds: int = 2, methods=None, sigma0=None) -> dict:
    from sim.lensopt.brief import DesignBrief
    from sim.lensopt.objectives import Evaluator, bare_limit
    from sim.lensopt.search import METHODS, Problem, run_search
    from sim.lensopt.space import DesignSpace, apply_design, design_of
    from sim.scene import load_scene

    res, trajs = {}, {}
    for scene in ("paper", "default-v1"):
        base = load_scene(scene)
        brief = DesignBrief.from_scene(base)
        ev = Evaluator(rays=brief.rays, sampler=brief.sampler, seed=0, grid=brief.grid, modes=brief.modes,
                       max_condition=brief.max_condition, region=brief.region)
        bare = ev((apply_design(base, brief.reference) if brief.reference else base).with_effects(remove=["lens"]))
        limits = {k: bare_limit(k, bare) if v == "bare" else float(v) for k, v in brief.constraints.items()}
        for method in methods or METHODS:
            for seed in range(seeds):
                prob = Problem(DesignSpace(base, dict(brief.vary)), ev, brief.objective, limits, brief.manufacturing)
                t0 = time.perf_counter()
                best, _, traj = run_search(prob, {**design_of(base), **brief.start}, method=method,
                                           evaluations=evaluations, seed=seed, sigma0=sigma0 or brief.sigma0,
                                           progress=False)
                sec = time.perf_counter() - t0
                value = best.objective_value(brief.objective) if best.feasible else None
                tag = f"{method}" + (f"@{sigma0:g}" if sigma0 else "")
                res[f"{scene}/{tag}/{seed}"] = {"objective": brief.objective, "best": value,
                                                   "feasible": best.feasible, "seconds": sec,
                                                   "evaluations": len(traj.loss), "traced": prob.traced}
                trajs[f"{scene} {tag} seed {seed}"] = traj.as_dict()
                rows.append({"knob": f"lens optimizer ({scene} brief)", "setting": f"{tag} seed {seed}",
                             "error": None if value is None else 1.0 - value, "error_unit": "fraction off screen",
                             "seconds": sec})
    if plot:
        from pathlib import Path

        from sim.lensopt.plot import trajectory_figure

        for scene in ("paper", "default-v1"):
            p = Path(plot)
            trajectory_figure({k.split(" ", 1)[1]: v for k, v in trajs.items() if k.startswith(scene + " ")},
                              p.with_name(f"{p.stem}_{scene}{p.suffix}"), objective="flux", label=f"{scene} brief: ")
    return res


def _smoothness() -> dict:
    from sim.lensopt.objectives import Evaluator
    from sim.lensopt.space import LENGTHS, apply_design, design_of
    from sim.scene import load_scene

    s = load_scene("paper-optimized")
    ev = Evaluator(rays=30_000, grid=30)
    m0 = ev(s)
    d0 = design_of(s)
    out = {}
    for k in LENGTHS:
        row = {}
        for h in (1e-3, 1e-2, 1e-1, 1.0):
            try:
                m = ev(apply_design(s, {k: d0[k] + h}))
            except Exception:  # noqa: BLE001 - a step that leaves no lens has no derivative
                continue
            row[f"{h:g}"] = {"d_flux_per_mm": (m.fraction_on_screen - m0.fraction_on_screen) / h,
                             "d_cv_per_mm": (m.uniformity_cv - m0.uniformity_cv) / h}
        out[k] = row
    return out


def format_table(result: dict) -> str:
    lines = [f"load average at start {result['load_average_start'][0]:.2f}, at end {result['load_average_end'][0]:.2f}"]
    for scene, r in (result.get("targets") or {}).items():
        vf = "-" if r["valid_fraction"] is None else f"{100 * r['valid_fraction']:.1f} %"
        lines.append(f"{scene:8s} target {r['target']}: {'MET' if r['met'] else 'NOT MET'} -- "
                     f"{100 * r['fraction_on_screen']:.2f} % on screen (bare {100 * r['bare_fraction_on_screen']:.2f}), "
                     f"CV {r['uniformity_cv']:.4f} (bare {r['bare_uniformity_cv']:.4f}), valid {vf}; "
                     f"{r['evaluations']} designs in {r['seconds']:.1f} s")
    if result.get("methods"):
        lines.append(f"{'scene/method/seed':<28} {'best':>10} {'seconds':>9} {'designs':>8} {'traced':>7}")
        for k, r in result["methods"].items():
            f = "none feasible" if r["best"] is None else f"{100 * r['best']:.2f} %"
            lines.append(f"{k:<28} {f:>10} {r['seconds']:>9.1f} {r['evaluations']:>8} {r['traced']:>7}")
    for k, row in (result.get("smoothness") or {}).items():
        lines.append(f"d/d {k:<11} " + "  ".join(f"h {h}: flux {v['d_flux_per_mm']:+.4f}/mm CV {v['d_cv_per_mm']:+.4f}/mm"
                                                  for h, v in row.items()))
    return "\n".join(lines)
