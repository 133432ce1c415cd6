"""Lens design: trace a scene with and without its lens, and search lens shapes.

:func:`trace_report` is what ``iristac sim trace`` prints; :func:`optimize_lens` searches the
side arc's radius and centre and the top radius within bounds for the largest flux on screen
whose 24-LED image keeps a coefficient of variation under a limit (``iristac sim
optimize-lens``).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, replace

import numpy as np

from pipeline.base.errors import UserError
from sim.optics.grid import PixelGrid
from sim.optics.metrics import image_metrics
from sim.optics.multisource import trace_all
from sim.scene import Scene, load_scene

__all__ = ["TRACE_KEYS", "trace_report", "compare_lens", "optimize_lens", "LensCandidate"]

#: The stable key set of ``iristac sim trace --json``.
TRACE_KEYS = ("fraction_on_screen", "mean_intensity", "uniformity_cv", "min_max", "channels", "rays", "seconds",
              "rays_per_second", "compile_seconds", "energy_residual", "scene", "lens", "sampler", "method",
              "intersection", "device", "engine", "dtype", "counters")


def _scene(scene) -> Scene:
    return scene if isinstance(scene, Scene) else load_scene(scene)


def trace_report(scene, *, rays: int | None = None, sampler: str | None = None, seed: int | None = None,
                 no_lens: bool = False, method: str = "hits", device="cpu", dtype=None,
                 images: bool = False, intersection: str | None = None, engine: str | None = None,
                 threads: int | None = None) -> dict:
    """Trace every LED of ``scene`` onto its imaging plane and report the paper's figures.

    Returns a dict with the keys :data:`TRACE_KEYS` (``rays`` per traced source; ``seconds``
    the wall time of the whole trace including binning, without ``compile_seconds``, the
    kernel's one-time compile or cache load in this process; ``rays_per_second`` the traced rays
    over ``seconds``; ``energy_residual`` the largest
    ``|emitted - (on screen + elsewhere + reflected + absorbed)|`` of the traced sources;
    ``engine`` the tracer that ran, :func:`sim.optics.engine.resolve_engine`), plus ``image``
    (H, W, 3) when ``images`` is set.

    Examples
    --------
    >>> r = trace_report("plano-sphere", rays=10_000)
    >>> sorted(k for k in TRACE_KEYS if k not in r), r["rays"], r["energy_residual"] < 1e-6
    ([], 10000, True)
    """
    s = _scene(scene)
    if no_lens:
        s = s.with_effects(remove=["lens"])
    from sim.optics import engine as _engine

    kind = _engine.resolve_engine(engine, intersection or s.trace.intersection)
    comp = _engine.warm_up(dtype, device) if kind == "kernel" else 0.0
    t0 = time.perf_counter()
    indices = s.lens.channel_indices() if s.has("dispersion") else (None,)
    results = [trace_all(s, PixelGrid.from_plane(s.plane), method=method, rays=rays, sampler=sampler, seed=seed,
                         vector=False, device=device, dtype=dtype, refractive_index=n_ch,
                         intersection=intersection, engine=kind, threads=threads)
               for n_ch in indices]
    secs = time.perf_counter() - t0
    Es = [r.E[0].astype(np.float64) for r in results]
    E = np.stack(Es) if len(Es) > 1 else Es[0]
    res = results[0]
    traces = [t for r in results for t in r.traces]
    m = image_metrics(E, s.leds.rgb, np.mean([r.fraction_on_grid for r in results], axis=0))
    n = sum(t.rays for t in traces)
    counters: dict = {}
    for t in traces:
        for k, v in t.counters.items():
            counters[k] = counters.get(k, 0) + v
    out = {**m, "rays": int(res.traces[0].rays), "seconds": secs, "rays_per_second": n / secs if secs > 0 else 0.0,
           "compile_seconds": comp, "energy_residual": max(abs(t.energy.residual) for t in traces), "scene": s.name,
           "lens": s.has("lens"), "sampler": sampler or s.trace.sampler, "method": method, "device": str(device),
           "intersection": intersection or s.trace.intersection, "engine": kind,
           "dtype": _engine.float_dtype(dtype).name, "counters": counters}
    if images:
        from sim.optics.metrics import pattern_image

        out["image"] = (np.stack([pattern_image(E[j], s.leds.rgb)[..., j] for j in range(3)], axis=2)
                        if E.ndim == 4 else pattern_image(E, s.leds.rgb))
    return out


def compare_lens(scene, **kw) -> dict:
    """``{"with_lens": report, "without_lens": report}`` (the paper's 63.5 % -> 78.0 % comparison)."""
    return {"with_lens": trace_report(scene, **kw), "without_lens": trace_report(scene, no_lens=True, **kw)}


@dataclass
class LensCandidate:
    arc_radius: float
    centre_rho: float
    centre_z: float
    top_radius: float
    fraction_on_screen: float = float("nan")
    uniformity_cv: float = float("nan")
    valid: bool = True
    reason: str = ""


def optimize_lens(scene, *, arc_radius=(10.0, 16.0), centre_rho=(24.0, 32.0), centre_z=(6.0, 14.0),
                  top_radius=(200.0, 1000.0), steps: int = 3, max_cv: float = 0.5, rays: int = 20_000,
                  refine: int = 1, device="cpu", engine: str | None = None) -> dict:
    """Grid search (then a finer grid around the best) over the lens shape.

    Maximises the flux fraction on screen subject to the 24-LED white image's coefficient of
    variation ``<= max_cv`` (if no design meets it, the most uniform one). Geometries that do not
    close into a valid lens (or that would put an LED inside it) are skipped and counted. Every
    candidate is traced by ``engine`` (default: the compiled kernel, :func:`trace_report`).

    Returns ``{"best": LensCandidate, "start": LensCandidate, "evaluated": int, "invalid": int,
    "scene": Scene (the best design), "start_scene": Scene}``.
    """
    base = _scene(scene)
    if base.lens is None or not base.lens.is_arc:
        raise UserError(f"optimize-lens: scene {base.name!r} needs a lens with a swept-arc side")
    bounds = {"arc_radius": arc_radius, "centre_rho": centre_rho, "centre_z": centre_z, "top_radius": top_radius}
    for k, (lo, hi) in bounds.items():
        if not lo <= hi:
            raise UserError(f"optimize-lens: bound {k} must be (low, high) with low <= high, got {(lo, hi)}")

    def evaluate(params):
        c = LensCandidate(**params)
        try:
            s = base.with_lens(**params)
        except (UserError, ValueError) as exc:
            c.valid, c.reason = False, str(exc)
            return c, None
        # Uniformity on a coarse 30 x 30 grid of the same screen: with few rays per candidate
        # the full-resolution CV would measure Monte Carlo noise rather than the design.
        coarse = replace(s, plane=replace(s.plane, resolution=(30, 30)))
        r = trace_report(coarse, rays=rays, sampler="sobol", device=device, engine=engine)
        c.fraction_on_screen, c.uniformity_cv = r["fraction_on_screen"], r["uniformity_cv"]
        return c, s

    def better(c, b):
        """Feasible beats infeasible; among feasible more flux wins; among infeasible lower CV."""
        cf, bf = c.uniformity_cv <= max_cv, b.uniformity_cv <= max_cv
        if cf != bf:
            return cf
        return c.fraction_on_screen > b.fraction_on_screen if cf else c.uniformity_cv < b.uniformity_cv

    ln = base.lens
    start, start_scene = evaluate({"arc_radius": ln.arc_radius, "centre_rho": ln.centre_rho,
                                   "centre_z": ln.centre_z, "top_radius": ln.top_radius})
    best, best_scene = start, start_scene
    evaluated, invalid = 1, 0
    lo_hi = dict(bounds)
    for level in range(refine + 1):
        axes = {k: np.linspace(lo, hi, steps) if hi > lo else np.array([lo]) for k, (lo, hi) in lo_hi.items()}
        for combo in itertools.product(*axes.values()):
            params = {k: float(v) for k, v in zip(axes, combo)}
            c, s = evaluate(params)
            evaluated += 1
            if not c.valid:
                invalid += 1
                continue
            if better(c, best):
                best, best_scene = c, s
        # Zoom in around the best point, staying inside the original bounds.
        lo_hi = {}
        for k, (lo, hi) in bounds.items():
            half = (hi - lo) / max(steps - 1, 1) / 2.0
            v = getattr(best, k)
            lo_hi[k] = (max(lo, v - half), min(hi, v + half))
    return {"best": best, "start": start, "evaluated": evaluated, "invalid": invalid, "scene": best_scene,
            "start_scene": start_scene}
