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
from sim.optics.base import Vec, box_interval
from sim.optics.lens import BOTTOM, TOP, LensBody
from sim.optics.plane import plane_hit
from sim.optics.binning import bin_passes
from sim.optics.sampling import SquareSampler, actual_rays, emission_directions, grid_points

__all__ = ["Energy", "SourceTrace", "trace_source", "lens_kernel", "lens_rays", "sum_stats", "DEFAULT_CHUNK",
           "FUSED_NEWTON_CAP"]

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
    every ray does (masks instead of branches), so the whole chunk is one fused graph (the
    fused tracer, :func:`trace_source` with ``compile``, calls :func:`lens_rays` instead).
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
    """One LED's rays, as plain values (the compiled tracer keys on it)."""

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
    # Summed in float64: the compiled reduction of a float32 chunk drifts by ~3e-5 otherwise.
    return torch.where(on, w, torch.zeros_like(w)).sum(dtype=torch.float64), w.sum(dtype=torch.float64)


# Newton steps of the fused path's swept-arc solves (entry, exit; 10 eagerly). After 6 entry
# steps about 0.2 % of the default scene's rays are still moving; those are traced again by the
# eager path (5 steps leave 0.9 %, 7 leave 0.05 %: 6 measured fastest). The exit solve starts
# at the top's exit, where no ray of the default scene needs a step; any that does is retraced
# (one masked exit step for every ray measured 5 ns per ray, more than the whole retrace).
FUSED_NEWTON_CAP = (6, 0)

_FUSED: dict = {}
_BODIES: dict = {}


def _body(lens, iterations: int) -> LensBody:
    """One :class:`LensBody` per lens and iteration count, so compiled code is reused across calls."""
    key = (repr(lens), iterations)
    if key not in _BODIES:
        _BODIES[key] = LensBody(lens, iterations=iterations)
    return _BODIES[key]


def _fused_chunk(body, ng, fresnel: bool, bounces: int, emitter: _Emitter, plane_z: float, half: tuple, layouts,
                 grid: bool = False, cap: tuple = FUSED_NEWTON_CAP):
    """``torch.compile`` of one whole chunk (cached): emission, lens, energy sums and bin indices.

    The compiled function takes square samples ``u, v`` (with ``grid``: the grid sampler's
    float64 cell indices and its ``k`` as a 0-d tensor, the points then made in the loop) and
    the ray power ``w0`` (0-d) and returns ``(stats, on_screen, total, passes, redo)``: summed
    lens statistics, the power on the scene's plane and in all,
    :func:`sim.optics.binning.bin_passes` per layout (masks, no compaction), and the rays whose
    capped Newton solve did not finish (``None`` without a lens), which are left out of
    everything else and must be traced again.

    Every key shares one code object, so past torch's recompile limit (8) in one process a new
    configuration runs this function uncompiled: the same results, at eager speed.
    """
    key = (id(body), ng, fresnel, bounces, emitter, plane_z, half, tuple(layouts), grid, cap)
    if key not in _FUSED:
        def chunk(a, b, w0):
            u, v = grid_points(a, b, w0.dtype) if grid else (a, b)
            o, d = emitter.rays(u, v)
            w = torch.ones_like(u) * w0
            stats, redo = {}, None
            if body is not None:
                o, d, w, per = lens_rays(body, ng, fresnel, bounces, o, d, w, cap=cap)
                redo = per["unfinished"]
                stats = sum_stats(per, keep=~redo)
                w = torch.where(redo, torch.zeros_like(w), w)
            won, wsum = _on_screen(o, d, w, plane_z, half)
            return stats, won, wsum, [bin_passes(lay, o, d, w, compact=False) for lay in layouts], redo

        # Floats stay constants (only the chunk length is symbolic), and one kernel may hold the
        # whole chunk: inductor's default caps a fused kernel at 64 nodes, which cut this graph
        # into three loops passing ~35 chunk-sized buffers through memory (measured 1.9x slower).
        compiled = torch.compile(chunk, dynamic=False, options={"max_fusion_size": 1 << 16})

        def run(a, b, w0):
            for x in (a, b):
                if x.dim():
                    torch._dynamo.mark_dynamic(x, 0)
            return compiled(a, b, w0)

        _FUSED[key] = (body, run)
    return _FUSED[key][1]


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
        Trace each chunk with one ``torch.compile``d function (robust intersection only):
        emission, lens, energy and bin indices fused into a few loops, the swept-arc solves
        capped at :data:`FUSED_NEWTON_CAP` steps with the rays they leave unfinished traced
        again eagerly; only the scatter into the images stays eager. Same results to
        rounding; the first call compiles for tens of seconds, so tests mostly leave it off.

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
    src = tuple(float(c) for c in pos[led])
    profile = scene.has("emission_profile")
    azimuth = math.atan2(src[1], src[0]) if (src[0] or src[1]) else 0.0
    emitter = _Emitter(src, tuple(float(c) for c in axes[led]), azimuth, float(scene.leds.emission_m),
                       float(scene.leds.cone_half_angle_deg), profile)
    use_lens = scene.has("lens")
    fresnel = scene.has("fresnel")
    bounces = scene.internal_bounces if scene.has("internal_bounces") else 0
    method = intersection or tr.intersection
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

    def book(stats, won, wsum):
        if stats:
            energy.reflected += float(stats["reflected"])
            energy.absorbed += float(stats["absorbed"])
            counters["tir_absorbed" if bounces == 0 else "bounce_limit"] += int(stats["tir_lost"])
            for key in ("tir_bounces", "aperture_absorbed", "numerical_lost", "newton_unconverged"):
                counters[key] += int(stats[key])
        won = float(won)
        energy.on_screen += won
        energy.elsewhere += float(wsum) - won

    def eager(u, v):
        o, d = emitter.rays(u, v)
        w = torch.full_like(u, w0)
        stats = {}
        if use_lens:
            instrument.count("lens")
            o, d, w, stats = lens_kernel(body, ng, fresnel, bounces, o, d, w, paper=paper)
        book(stats, *_on_screen(o, d, w, plane.z, half))
        for acc in accumulators:
            acc.add(o, d, w)

    fused = None
    grid = kind == "grid"
    if compile and paper is None:
        fused = _fused_chunk(body if use_lens else None, ng, fresnel, bounces, emitter, float(plane.z), half,
                             [acc.layout for acc in accumulators], grid)
        w0_t = torch.tensor(w0, device=smp.device, dtype=dtype)
        k_t = torch.tensor(float(smp.k), device=smp.device, dtype=torch.float64)
        counters["retraced"] = 0
    retrace = []
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        energy.emitted += (stop - start) * w0
        if fused is None:
            eager(*smp.draw(start, stop))
            continue
        # The grid sampler's points are made in the compiled loop.
        a, b = (smp.indices(start, stop), k_t) if grid else smp.draw(start, stop)
        # What the compiled code ran (instrument.count is a no-op inside it).
        if profile:
            instrument.count("emission_profile")
        if use_lens:
            instrument.count("lens")
            if fresnel:
                instrument.count("fresnel", bounces + 2)
            if bounces:
                instrument.count("internal_bounces", bounces)
        stats, won, wsum, passes, redo = fused(a, b, w0_t)
        book(stats, won, wsum)
        for acc, p in zip(accumulators, passes):
            acc.add_passes(p, compiled=True)
        if redo is not None:
            idx = torch.nonzero(redo).squeeze(1)
            if idx.numel():
                retrace.append(grid_points(a[idx], smp.k, dtype) if grid else (a[idx], b[idx]))
    if retrace:
        # The rays the capped solves left unfinished, through the eager path in one go (a call
        # per chunk costs ~2 ms of per-op overhead, for ~0.2 % of the rays).
        u, v = (torch.cat(x) for x in zip(*retrace))
        counters["retraced"] = len(u)
        for start in range(0, len(u), chunk):
            eager(u[start:start + chunk], v[start:start + chunk])
    if paper is not None:
        counters.update(paper.counters)
    return SourceTrace(led=led, rays=n, seconds=time.perf_counter() - t0, energy=energy, counters=counters)
