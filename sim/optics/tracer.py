"""The chunked Monte Carlo tracer: one LED's rays through the lens to the gel.

:func:`trace_source` runs one of two engines (:func:`sim.optics.engine.resolve_engine`): the
compiled kernel (:mod:`sim.optics.kernel`, the default for the robust intersection) or the
eager torch code of this module, the reference, which every physics test also runs.

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
from dataclasses import dataclass

import torch

from sim.optics import engine as _engine
from sim.optics import instrument
from sim.optics.base import Vec, box_interval
from sim.optics.energy import Energy, SourceTrace
from sim.optics.interface import fresnel_transmittance, reflect, refract
from sim.optics.lens import BOTTOM, TOP, LensBody
from sim.optics.plane import plane_hit
from sim.optics.sampling import SquareSampler, actual_rays, emission_directions

__all__ = ["Energy", "SourceTrace", "trace_source", "lens_kernel", "lens_rays", "sum_stats", "DEFAULT_CHUNK"]

DEFAULT_CHUNK = 1 << 19


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

    Only the rays that enter the lens go on through it.
    """
    *out, per = lens_rays(body, ng, fresnel, bounces, o, d, w, paper=paper)
    return (*out, sum_stats(per))


def lens_rays(body: LensBody, ng: float, fresnel: bool, bounces: int, o: Vec, d: Vec, w, paper=None,
              cap: tuple | None = None):
    """:func:`lens_kernel` with its statistics per ray, not summed: ``(o_out, d_out, w_out, per)``.

    ``per`` maps each statistic to a list of tensors to be summed (:func:`sum_stats`), over
    all rays or over the rays that entered the lens. With ``cap = (entry, exit)`` every ray goes
    through (masks, no compaction), the swept-arc solves take at most that many Newton steps, and
    ``per["unfinished"]`` (bool, every ray) marks the rays they left short of the root: their
    results are not to be used (the fused tracer retraces them without the cap).
    """
    # The lens's bounding box once per chunk (enter() reuses it). Eagerly, only the rays that
    # enter the lens go on; compacting earlier, to the rays in the box, measured slower
    # (gathers and scatters cost more than they save).
    t, sid, hit, unconv, unfinished = body.enter_capped(o, d, box_interval(o, d, *body.box),
                                                       None if cap is None else cap[0])
    if cap is None and not torch.compiler.is_compiling() and not bool(hit.all()):
        idx = torch.nonzero(hit).squeeze(1)
        so, sd, sw, per = _through(body, ng, fresnel, bounces, tuple(c[idx] for c in o), tuple(c[idx] for c in d),
                                   w[idx], t[idx], sid[idx], hit[idx], paper, None)
        out = (tuple(c.index_put((idx,), x) for c, x in zip(o, so)),
               tuple(c.index_put((idx,), x) for c, x in zip(d, sd)), w.index_put((idx,), sw))
    else:
        *out, per = _through(body, ng, fresnel, bounces, o, d, w, t, sid, hit, paper, cap)
    per["newton_unconverged"] = [unconv]
    if cap is not None:
        late = per.pop("unfinished", torch.zeros_like(hit))
        per["unfinished"] = late if unfinished is None else unfinished | late
    return (*out, per)


def sum_stats(per: dict, keep=None) -> dict:
    """Sum :func:`lens_rays`'s per-ray statistics, over the rays ``keep`` (bool, every ray) if given."""
    out = {}
    for name, parts in per.items():
        if name == "unfinished":
            continue
        total = None
        for x in parts:
            if keep is not None:
                x = (x & keep) if x.dtype == torch.bool else torch.where(keep, x, torch.zeros_like(x))
            part = x.sum() if x.dtype == torch.bool else x.sum(dtype=torch.float64)
            total = part if total is None else total + part
        out[name] = total
    return out


def _through(body: LensBody, ng: float, fresnel: bool, bounces: int, o: Vec, d: Vec, w, t, sid, hit, paper, cap):
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
    per = {"tir_lost": [], "tir_bounces": [], "aperture_absorbed": [stop], "numerical_lost": []}
    unfinished = None
    for k in range(bounces + 1):
        t, sid, good, late = body.leave_capped(p_cur, d_cur, None if cap is None else cap[1])
        if late is not None:
            late = inside & late
            unfinished = late if unfinished is None else unfinished | late
        q = _along(p_cur, d_cur, t)
        nrm = body.normal(q, sid)
        if paper is not None:
            q, nrm = paper.exit(p_cur, d_cur, q, nrm, sid, inside & good)
        inward = (-nrm[0], -nrm[1], -nrm[2])
        dt, ci, ct, tir = refract(d_cur, inward, ng)
        stop = inside & good & _stopped(body.lens, q, sid)
        lost = inside & ~good
        absorbed = absorbed + torch.where(lost | stop, w_in, zero)
        per["aperture_absorbed"].append(stop)
        per["numerical_lost"].append(lost)
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
            instrument.count("internal_bounces")
            per["tir_bounces"].append(trap)
            d_cur = _where(trap, reflect(d_cur, inward), d_cur)
            p_cur = _where(trap, q, p_cur)
            inside = trap
        else:
            absorbed = absorbed + torch.where(trap, w_in, zero)
            per["tir_lost"].append(trap)
    per["reflected"] = [reflected]
    per["absorbed"] = [absorbed]
    if not per["tir_bounces"]:
        per["tir_bounces"] = [torch.zeros_like(hit)]
    if unfinished is not None:
        per["unfinished"] = unfinished
    return out_o, out_d, out_w, per


@dataclass(frozen=True)
class _Emitter:
    """One LED's rays, as plain values."""

    src: tuple
    axis: tuple
    azimuth: float
    m: float
    cone_deg: float
    profile: bool

    def rays(self, u, v):
        """Origins and unit directions of the rays of square samples ``u, v``."""
        d = emission_directions(u, v, self.m, self.cone_deg, self.axis, profile=self.profile, azimuth=self.azimuth)
        return tuple(torch.full_like(u, c) for c in self.src), d


def _on_screen(o: Vec, d: Vec, w, plane_z: float, half: tuple):
    """``(power on the scene's imaging plane, total power)`` of rays leaving the optics (0-d tensors)."""
    x, y, _, fwd = plane_hit(o, d, plane_z)
    on = fwd & (x.abs() <= half[0]) & (y.abs() <= half[1])
    # Summed in float64: a float32 sum over a chunk drifts by ~3e-5 otherwise.
    return torch.where(on, w, torch.zeros_like(w)).sum(dtype=torch.float64), w.sum(dtype=torch.float64)


_BODIES: dict = {}


def _body(lens, iterations: int) -> LensBody:
    """One :class:`LensBody` per lens and iteration count."""
    key = (repr(lens), iterations)
    if key not in _BODIES:
        _BODIES[key] = LensBody(lens, iterations=iterations)
    return _BODIES[key]


def trace_source(scene, accumulators=(), *, led: int = 0, rays: int | None = None, sampler: str | None = None,
                 seed: int | None = None, device="cpu", dtype=torch.float32, chunk: int = DEFAULT_CHUNK,
                 refractive_index: float | None = None, intersection: str | None = None,
                 newton_iterations: int | None = None, body: LensBody | None = None,
                 engine: str | None = None, threads: int | None = None) -> SourceTrace:
    """Trace one LED of ``scene`` and feed the rays leaving the optics to ``accumulators``.

    Parameters
    ----------
    scene : sim.scene.Scene
    accumulators : sequence of sim.optics.binning.FieldAccumulator or sim.optics.grid.ImageBins
        Each receives every ray that leaves the optics (origin, direction, power); the kernel
        engine bins them itself and adds its images.
    led : int
        Which LED of the ring.
    rays, sampler, seed : optional
        Override the scene's trace defaults.
    device, dtype :
        Device (``cpu``, ``cuda``...) and float type (float32 by default; float64 for references).
    chunk : int
        Rays per chunk of the torch engine: bounds memory whatever the ray count (the kernel
        makes its rays in blocks and needs no chunks).
    refractive_index : float, optional
        Override the lens's index (the dispersion effect traces once per channel index).
    intersection : {"robust", "paper"}, optional
        How the lens surfaces are intersected (see :mod:`sim.optics.paper_cases`; the paper's
        method runs on the torch engine only).
    newton_iterations : int, optional
        Iterations of the swept-arc solve (robust) or of the paper's case-2 Newton (paper).
    engine : {"kernel", "torch"}, optional
        The compiled kernel (default for the robust intersection) or the eager torch reference.
    threads : int, optional
        CPU threads of the kernel engine (:func:`sim.optics.engine.kernel_threads`).

    Returns
    -------
    SourceTrace
    """
    tr = scene.trace
    method = intersection or tr.intersection
    if _engine.resolve_engine(engine, method, scene) == "kernel":
        images, res = _engine.trace_led(scene, [acc.layout for acc in accumulators], led=led, rays=rays,
                                        sampler=sampler, seed=seed, dtype=dtype, device=device,
                                        refractive_index=refractive_index, newton_iterations=newton_iterations,
                                        threads=threads)
        for acc, img in zip(accumulators, images):
            acc.add_binned(img)
        return res
    return _trace_torch(scene, accumulators, led=led, rays=rays, sampler=sampler, seed=seed, device=device,
                        dtype=dtype, chunk=chunk, refractive_index=refractive_index, method=method,
                        newton_iterations=newton_iterations, body=body)


def _trace_torch(scene, accumulators, *, led: int, rays: int | None, sampler: str | None, seed: int | None,
                 device, dtype, chunk: int, refractive_index: float | None, method: str,
                 newton_iterations: int | None, body: LensBody | None) -> SourceTrace:
    """:func:`trace_source` on the eager torch engine: rays drawn and traced through the lens in
    chunks of ``chunk``, each chunk's rays leaving the optics fed to ``accumulators``."""
    tr = scene.trace
    t0 = time.perf_counter()
    kind = sampler or tr.sampler
    n = actual_rays(int(rays if rays is not None else tr.rays), kind)
    smp = SquareSampler(n, kind, seed=tr.seed if seed is None else seed, device=device, dtype=dtype)
    pos, axes = scene.leds.geometry()
    src = tuple(float(c) for c in pos[led])
    profile = scene.has("emission_profile")
    azimuth = math.atan2(src[1], src[0]) if (src[0] or src[1]) else 0.0
    emitter = _Emitter(src, tuple(float(c) for c in axes[led]), azimuth, float(scene.leds.emission_m),
                       float(scene.leds.cone_half_angle_deg), profile)
    use_lens = scene.has("lens")
    fresnel = scene.has("fresnel")
    bounces = scene.internal_bounces if scene.has("internal_bounces") else 0
    paper = None
    ng = None
    if use_lens:
        ng = float(refractive_index if refractive_index is not None else scene.lens.refractive_index)
        if method == "paper":
            from sim.optics.paper_cases import PaperIntersector

            paper = PaperIntersector(scene.lens, iterations=newton_iterations or tr.newton_iterations)
        if body is None:
            body = _body(scene.lens, newton_iterations if method == "robust" and newton_iterations else 10)
    energy = Energy()
    counters = {"tir_absorbed": 0, "tir_bounces": 0, "bounce_limit": 0, "aperture_absorbed": 0,
                "numerical_lost": 0, "newton_unconverged": 0}
    plane = scene.plane
    half = (plane.size[0] / 2.0, plane.size[1] / 2.0)
    w0 = 1.0 / n
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        energy.emitted += (stop - start) * w0
        u, v = smp.draw(start, stop)
        o, d = emitter.rays(u, v)
        w = torch.full_like(u, w0)
        if use_lens:
            instrument.count("lens")
            o, d, w, stats = lens_kernel(body, ng, fresnel, bounces, o, d, w, paper=paper)
            energy.reflected += float(stats["reflected"])
            energy.absorbed += float(stats["absorbed"])
            counters["tir_absorbed" if bounces == 0 else "bounce_limit"] += int(stats["tir_lost"])
            for key in ("tir_bounces", "aperture_absorbed", "numerical_lost", "newton_unconverged"):
                counters[key] += int(stats[key])
        won, wsum = _on_screen(o, d, w, plane.z, half)
        won = float(won)
        energy.on_screen += won
        energy.elsewhere += float(wsum) - won
        for acc in accumulators:
            acc.add(o, d, w)
    if paper is not None:
        counters.update(paper.counters)
    return SourceTrace(led=led, rays=n, seconds=time.perf_counter() - t0, energy=energy, counters=counters,
                       engine="torch")

