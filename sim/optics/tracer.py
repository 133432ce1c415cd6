"""The chunked Monte Carlo tracer: one LED's rays through the lens to the gel.

For each chunk of rays: sample equal-power directions from the LED's emission profile, enter
the lens (refraction and Fresnel transmission at the entry surface), leave it (refraction and
Fresnel again; total internal reflection absorbs the ray, or reflects it for up to K internal
bounces when the scene asks), then hand the rays leaving the optics to accumulators that bin
them on pixel grids. Only the effects the scene lists are computed.

Energy bookkeeping per LED (unit power): ``emitted = on_screen + elsewhere + reflected +
absorbed``, each summed independently, so the residual is a real check.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch

from sim.optics import instrument
from sim.optics.interface import fresnel_transmittance, reflect, refract
from sim.optics.base import Vec
from sim.optics.lens import BOTTOM, TOP, LensBody, box_interval
from sim.optics.plane import plane_hit
from sim.optics.sampling import SquareSampler, actual_rays, emission_directions

__all__ = ["Energy", "SourceTrace", "trace_source", "lens_kernel", "DEFAULT_CHUNK"]

DEFAULT_CHUNK = 1 << 19


@dataclass
class Energy:
    """Where one LED's unit power went (fractions of the emitted power)."""

    emitted: float = 0.0
    on_screen: float = 0.0
    elsewhere: float = 0.0
    reflected: float = 0.0
    absorbed: float = 0.0

    @property
    def residual(self) -> float:
        """``emitted - (on_screen + elsewhere + reflected + absorbed)``: zero to rounding."""
        return self.emitted - (self.on_screen + self.elsewhere + self.reflected + self.absorbed)

    def as_dict(self) -> dict:
        return {"emitted": self.emitted, "on_screen": self.on_screen, "elsewhere": self.elsewhere,
                "reflected": self.reflected, "absorbed": self.absorbed, "residual": self.residual}


@dataclass
class SourceTrace:
    """What tracing one LED produced besides the accumulated images."""

    led: int
    rays: int
    seconds: float
    energy: Energy
    counters: dict = field(default_factory=dict)


def _where(m, a: Vec, b: Vec) -> Vec:
    return tuple(torch.where(m, x, y) for x, y in zip(a, b))


def _along(o: Vec, d: Vec, t) -> Vec:
    return o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]


def _stopped(lens, p: Vec, sid):
    """Bool (N,): crossing the top or bottom outside its clear aperture (a housing stop)."""
    stop = torch.zeros_like(sid, dtype=torch.bool)
    for surf, ap in ((TOP, lens.top_aperture), (BOTTOM, lens.bottom_aperture)):
        if ap is not None:
            stop = stop | ((sid == surf) & (p[0] * p[0] + p[1] * p[1] > ap * ap))
    return stop


def lens_kernel(body: LensBody, ng: float, fresnel: bool, bounces: int, o: Vec, d: Vec, w, paper=None):
    """Every ray of a chunk through the lens.

    Returns ``(o_out, d_out, w_out, stats)``: the rays leaving the optics (rays that miss the
    lens pass unchanged; absorbed rays leave with ``w = 0``) and a dict of summed tensors
    ``reflected``, ``absorbed`` and counts ``tir_lost``, ``tir_bounces``,
    ``aperture_absorbed``, ``numerical_lost``, ``newton_unconverged``.

    Eagerly, only the rays that enter the lens go on through it; under ``torch.compile``
    every ray does (masks instead of branches), so the whole chunk is one fused graph.
    """
    # The lens's bounding box once per chunk (enter() reuses it). Eagerly, _lens_masked then
    # carries on with the rays that enter the lens only; compacting earlier, to the rays in the
    # box, measured slower (gathers and scatters cost more than they save).
    return _lens_masked(body, ng, fresnel, bounces, o, d, w, paper, box_interval(o, d, *body.box))


def _lens_masked(body: LensBody, ng: float, fresnel: bool, bounces: int, o: Vec, d: Vec, w, paper=None, box=None):
    """:func:`lens_kernel` with masks instead of branches (one fusable graph)."""
    t, sid, hit, unconv = body.enter(o, d, box)
    if not torch.compiler.is_compiling() and not bool(hit.all()):
        # Eager: only the rays that enter the lens go on through it.
        idx = torch.nonzero(hit).squeeze(1)
        so, sd, sw, stats = _through(body, ng, fresnel, bounces, tuple(c[idx] for c in o), tuple(c[idx] for c in d),
                                     w[idx], t[idx], sid[idx], hit[idx], paper)
        out = (tuple(c.index_put((idx,), x) for c, x in zip(o, so)),
               tuple(c.index_put((idx,), x) for c, x in zip(d, sd)), w.index_put((idx,), sw))
    else:
        *out, stats = _through(body, ng, fresnel, bounces, o, d, w, t, sid, hit, paper)
    stats["newton_unconverged"] = unconv.sum()
    return (*out, stats)


def _through(body: LensBody, ng: float, fresnel: bool, bounces: int, o: Vec, d: Vec, w, t, sid, hit, paper):
    """Rays ``hit`` enter the lens at ``o + t d`` through surface ``sid``: refract, cross, leave."""
    zero = torch.zeros_like(w)
    p = _along(o, d, t)
    nrm = body.normal(p, sid)
    if paper is not None:
        p, nrm = paper.entry(o, d, p, nrm, sid, hit)
    stop = hit & _stopped(body.lens, p, sid)
    d1, ci, ct, _ = refract(d, nrm, 1.0 / ng)
    if fresnel:
        T = fresnel_transmittance(ci, ct, 1.0, ng)
        reflected = torch.where(hit & ~stop, w * (1.0 - T), zero)
        w_in = w * T
    else:
        reflected = zero
        w_in = w
    absorbed = torch.where(stop, w, zero)
    inside = hit & ~stop
    out_o, out_d, out_w = o, d, torch.where(hit, zero, w)
    p_cur, d_cur = p, _where(hit, d1, d)
    tir_bounces = zero.new_zeros(())
    tir_absorbed = zero.new_zeros(())
    aperture = stop.sum().to(w.dtype)
    lost_n = zero.new_zeros(())
    for k in range(bounces + 1):
        t, sid, good = body.leave(p_cur, d_cur)
        q = _along(p_cur, d_cur, t)
        nrm = body.normal(q, sid)
        if paper is not None:
            q, nrm = paper.exit(p_cur, d_cur, q, nrm, sid, inside & good)
        inward = (-nrm[0], -nrm[1], -nrm[2])
        dt, ci, ct, tir = refract(d_cur, inward, ng)
        stop = inside & good & _stopped(body.lens, q, sid)
        lost = inside & ~good
        absorbed = absorbed + torch.where(lost | stop, w_in, zero)
        aperture = aperture + stop.sum()
        lost_n = lost_n + lost.sum()
        act = inside & good & ~stop
        ex = act & ~tir
        if fresnel:
            T = fresnel_transmittance(ci, ct, ng, 1.0)
            reflected = reflected + torch.where(ex, w_in * (1.0 - T), zero)
            w_ex = w_in * T
        else:
            w_ex = w_in
        out_o, out_d = _where(ex, q, out_o), _where(ex, dt, out_d)
        out_w = torch.where(ex, w_ex, out_w)
        trap = act & tir
        if k < bounces:
            if not torch.compiler.is_compiling():
                instrument.count("internal_bounces")
            tir_bounces = tir_bounces + trap.sum()
            d_cur = _where(trap, reflect(d_cur, inward), d_cur)
            p_cur = _where(trap, q, p_cur)
            inside = trap
        else:
            absorbed = absorbed + torch.where(trap, w_in, zero)
            tir_absorbed = tir_absorbed + trap.sum()
    stats = {"reflected": reflected.sum(), "absorbed": absorbed.sum(), "tir_lost": tir_absorbed,
             "tir_bounces": tir_bounces, "aperture_absorbed": aperture, "numerical_lost": lost_n}
    return out_o, out_d, out_w, stats


_COMPILED: dict = {}


def _compiled_kernel(body, ng, fresnel, bounces):
    """``torch.compile`` of :func:`lens_kernel` for one lens and flag set (cached)."""
    key = (id(body), ng, fresnel, bounces)
    if key not in _COMPILED:
        def f(ox, oy, oz, dx, dy, dz, w):
            return lens_kernel(body, ng, fresnel, bounces, (ox, oy, oz), (dx, dy, dz), w)

        _COMPILED[key] = (body, torch.compile(f, dynamic=True))
    return _COMPILED[key][1]


def trace_source(scene, accumulators=(), *, led: int = 0, rays: int | None = None, sampler: str | None = None,
                 seed: int | None = None, device="cpu", dtype=torch.float32, chunk: int = DEFAULT_CHUNK,
                 refractive_index: float | None = None, intersection: str | None = None,
                 newton_iterations: int | None = None, body: LensBody | None = None,
                 compile: bool = False) -> SourceTrace:
    """Trace one LED of ``scene`` and feed the rays leaving the optics to ``accumulators``.

    Parameters
    ----------
    scene : sim.scene.Scene
    accumulators : sequence of sim.optics.binning.FieldAccumulator
        Each receives every ray that leaves the optics (origin, direction, power).
    led : int
        Which LED of the ring.
    rays, sampler, seed : optional
        Override the scene's trace defaults.
    device, dtype :
        Torch device and float type (float32 by default; float64 for references).
    chunk : int
        Rays per chunk: bounds memory whatever the ray count.
    refractive_index : float, optional
        Override the lens's index (the dispersion effect traces once per channel index).
    intersection : {"robust", "paper"}, optional
        How the lens surfaces are intersected (see :mod:`sim.optics.paper_cases`).
    newton_iterations : int, optional
        Iterations of the swept-arc solve (robust) or of the paper's case-2 Newton (paper).
    compile : bool
        Run the lens kernel through ``torch.compile`` (fused loops; the first call compiles
        for tens of seconds, so tests leave it off and the benchmark measures both).

    Returns
    -------
    SourceTrace
    """
    t0 = time.perf_counter()
    tr = scene.trace
    kind = sampler or tr.sampler
    n = actual_rays(int(rays if rays is not None else tr.rays), kind)
    smp = SquareSampler(n, kind, seed=tr.seed if seed is None else seed, device=device, dtype=dtype)
    pos, axes = scene.leds.geometry()
    src = [float(c) for c in pos[led]]
    axis = tuple(float(c) for c in axes[led])
    azimuth = math.atan2(src[1], src[0]) if (src[0] or src[1]) else 0.0
    use_lens = scene.has("lens")
    profile = scene.has("emission_profile")
    fresnel = scene.has("fresnel")
    bounces = scene.internal_bounces if scene.has("internal_bounces") else 0
    method = intersection or tr.intersection
    paper = None
    kernel = None
    if use_lens:
        ng = float(refractive_index if refractive_index is not None else scene.lens.refractive_index)
        if method == "paper":
            from sim.optics.paper_cases import PaperIntersector

            paper = PaperIntersector(scene.lens, iterations=newton_iterations or tr.newton_iterations)
        if body is None:
            body = LensBody(scene.lens, iterations=(newton_iterations if method == "robust" and newton_iterations
                                                    else 10))
        if compile and paper is None:
            kernel = _compiled_kernel(body, ng, fresnel, bounces)
    energy = Energy()
    counters = {"tir_absorbed": 0, "tir_bounces": 0, "bounce_limit": 0, "aperture_absorbed": 0,
                "numerical_lost": 0, "newton_unconverged": 0}
    plane = scene.plane
    half_w, half_h = plane.size[0] / 2.0, plane.size[1] / 2.0
    w0 = 1.0 / n
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        m = stop - start
        u, v = smp.draw(start, stop)
        d = emission_directions(u, v, scene.leds.emission_m, scene.leds.cone_half_angle_deg, axis, profile=profile,
                                 azimuth=azimuth)
        o = tuple(torch.full((m,), c, device=smp.device, dtype=dtype) for c in src)
        w = torch.full((m,), w0, device=smp.device, dtype=dtype)
        energy.emitted += m * w0
        if use_lens:
            instrument.count("lens")
            if kernel is not None:
                o, d, w, stats = kernel(*o, *d, w)
                if fresnel:
                    instrument.count("fresnel", 2)
                if bounces:
                    instrument.count("internal_bounces")
            else:
                o, d, w, stats = lens_kernel(body, ng, fresnel, bounces, o, d, w, paper=paper)
            energy.reflected += float(stats["reflected"])
            energy.absorbed += float(stats["absorbed"])
            counters["tir_absorbed" if bounces == 0 else "bounce_limit"] += int(stats["tir_lost"])
            for key in ("tir_bounces", "aperture_absorbed", "numerical_lost", "newton_unconverged"):
                counters[key] += int(stats[key])
        # The scene's imaging plane (for the energy budget), independent of any accumulator grid.
        x, y, _, fwd = plane_hit(o, d, plane.z)
        on = fwd & (x.abs() <= half_w) & (y.abs() <= half_h)
        won = float(torch.where(on, w, torch.zeros_like(w)).sum())
        energy.on_screen += won
        energy.elsewhere += float(w.sum()) - won
        for acc in accumulators:
            acc.add(o, d, w)
    if paper is not None:
        counters.update(paper.counters)
    return SourceTrace(led=led, rays=n, seconds=time.perf_counter() - t0, energy=energy, counters=counters)
