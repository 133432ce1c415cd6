"""Which tracer runs, and the compiled kernel's driver: scene -> parameter arrays -> images and books.

Two engines trace the same physics:

``kernel``  the compiled per-ray kernel (:mod:`sim.optics.kernel`, Numba; on CUDA devices
            :mod:`sim.optics.kernel_cuda`): emission, lens, energy books and binning in one
            pass, parallel over the CPU cores, compiled once and cached on disk. The default
            for the robust intersection.
``torch``   the eager torch tracer (:mod:`sim.optics.tracer`), the reference; also the only
            engine for the paper's intersection method, and for lens surfaces the kernel does
            not trace (each surface declares its engines: :mod:`sim.optics.surfaces`).

This module imports neither torch nor the tracer: a user's ``iristac sim trace`` runs the
kernel without paying for torch's import.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from sim.optics import instrument
from sim.optics.emitter import actual_rays, emitter_frame, profile_constants
from sim.optics.energy import Energy, SourceTrace
from sim.optics.grid import BinLayout

__all__ = ["ENGINES", "EngineFallback", "resolve_engine", "float_dtype", "kernel_params", "grid_tables", "pass_tables",
           "trace_led", "trace_cpu", "lens_rays", "warm_up", "compile_seconds", "kernel_threads", "cuda_available"]

ENGINES = ("kernel", "torch")

# Seconds each (float type, device) took to compile or load in this process.
_COMPILED: dict = {}


def float_dtype(dtype) -> np.dtype:
    """``float32`` or ``float64`` as a numpy dtype, from a numpy or torch dtype or a name (None: float32).

    Examples
    --------
    >>> float_dtype(None), float_dtype("float64")
    (dtype('float32'), dtype('float64'))
    """
    if dtype is None:
        return np.dtype(np.float32)
    name = str(dtype).replace("torch.", "")
    if name not in ("float32", "float64"):
        try:
            name = np.dtype(dtype).name
        except TypeError:
            pass
    if name not in ("float32", "float64"):
        raise ValueError(f"dtype must be float32 or float64, got {dtype!r}")
    return np.dtype(name)


class EngineFallback(UserWarning):
    """The default engine cannot trace a scene's lens and ``torch`` traces it instead."""


def resolve_engine(engine: str | None, intersection: str = "robust", scene=None) -> str:
    """The engine that traces: ``engine`` if given (checked), else ``kernel`` for the robust
    intersection and ``torch`` for the paper's (which only the reference implements). The
    scene's lens surfaces say which engines trace them (:mod:`sim.optics.surfaces`): a lens with
    a surface the kernel does not trace (a conic top) is traced by ``torch``, with an
    :class:`EngineFallback` warning that names the surface; asking for the kernel there is an
    error.

    Examples
    --------
    >>> resolve_engine(None), resolve_engine(None, "paper"), resolve_engine("torch")
    ('kernel', 'torch', 'torch')
    """
    from sim.optics.surfaces import SURFACES, engines_for, lens_surfaces

    surfaces = lens_surfaces(scene.lens) if scene is not None and scene.has("lens") else ()
    able = engines_for(surfaces)
    untraced = [s for s in surfaces if "kernel" not in SURFACES[s].engines]
    if engine is None:
        if intersection != "robust":
            return "torch"
        if "kernel" in able:
            return "kernel"
        import warnings

        warnings.warn(f"the kernel engine does not trace the lens's {' and '.join(untraced)} surface "
                      f"(sim/optics/surfaces.py); tracing with the torch engine", EngineFallback, stacklevel=2)
        return "torch"
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if engine == "kernel" and intersection != "robust":
        raise ValueError(f"the kernel engine implements the robust intersection only, not {intersection!r}; "
                         "use engine 'torch'")
    if engine not in able:
        raise ValueError(f"the {engine} engine does not trace this lens's {' and '.join(untraced)} surface "
                         f"(sim/optics/surfaces.py); use engine 'torch'")
    return engine


def _splitmix(x: int) -> int:
    m = (1 << 64) - 1
    z = (x + 0x9E3779B97F4A7C15) & m
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & m
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & m
    return z ^ (z >> 31)


def kernel_params(scene, *, led: int = 0, rays: int, sampler: str, seed: int = 0, dtype=np.float32,
                  refractive_index: float | None = None, newton_iterations: int = 10):
    """The kernel's view of one LED of ``scene``: ``(P, F, seeds)``.

    ``P`` (kernel float type) and ``F`` (int64) are indexed by :data:`sim.optics.kernel.P_SLOTS`
    and :data:`sim.optics.kernel.F_SLOTS`; ``seeds`` (uint64 (3,)) key the random and Sobol
    streams. ``rays`` is the actual count (:func:`sim.optics.emitter.actual_rays`).
    """
    from sim.optics import kernel as K

    if scene.has("lens"):
        resolve_engine("kernel", "robust", scene)  # a surface the kernel does not trace: one clear error
    ft = float_dtype(dtype)
    P = np.zeros(K.P_COUNT, dtype=np.float64)
    F = np.zeros(K.F_COUNT, dtype=np.int64)
    pos, axes = scene.leds.geometry()
    src = [float(c) for c in pos[led]]
    az = math.atan2(src[1], src[0]) if (src[0] or src[1]) else 0.0
    e1, e2, e3 = emitter_frame(axes[led], az)
    ca, sa = math.cos(az), math.sin(az)
    rot = lambda v: (ca * v[0] - sa * v[1], sa * v[0] + ca * v[1], v[2])  # noqa: E731
    cols = [rot(e) for e in (e1, e2, e3)]
    P[K.P_ONE] = 1.0
    P[K.P_SRC_X:K.P_SRC_Z + 1] = src
    P[K.P_M00:K.P_M22 + 1] = [cols[j][i] for i in range(3) for j in range(3)]
    a, e = profile_constants(scene.leds.emission_m, scene.leds.cone_half_angle_deg, scene.has("emission_profile"))
    P[K.P_EM_A], P[K.P_EM_EXP], P[K.P_TWO_PI] = a, e, 2.0 * math.pi
    F[K.F_EM_SQRT] = int(e == 0.5)
    P[K.P_W0] = 1.0 / rays
    P[K.P_INV_2_24] = 2.0 ** -24
    P[K.P_INF] = math.inf
    P[K.P_RHO_EPS] = 1e-12
    plane = scene.plane
    P[K.P_PLANE_Z], P[K.P_HALF_X], P[K.P_HALF_Y] = plane.z, plane.size[0] / 2.0, plane.size[1] / 2.0
    if scene.has("lens"):
        ln = scene.lens
        ng = float(refractive_index if refractive_index is not None else ln.refractive_index)
        F[K.F_LENS] = 1
        F[K.F_FRESNEL] = int(scene.has("fresnel"))
        F[K.F_BOUNCES] = scene.internal_bounces if scene.has("internal_bounces") else 0
        F[K.F_ITERATIONS] = int(newton_iterations)
        P[K.P_NG], P[K.P_ETA_IN] = ng, 1.0 / ng
        margin = 1e-3  # as sim.optics.lens.LensBody.box
        if ln.is_arc:
            F[K.F_ARC] = 1
            P[K.P_ARC_R1], P[K.P_ARC_RHOC], P[K.P_ARC_ZC] = ln.arc_radius, ln.centre_rho, ln.centre_z
            P[K.P_ARC_ZLO], P[K.P_ARC_ZHI] = ln.bottom_z, ln.rim_z
            # The side's widest radius: g is concave with its top at the arc centre's height.
            P[K.P_BOX_R] = float(ln.side_rho(min(max(ln.centre_z, ln.bottom_z), ln.rim_z))) + margin
        else:
            P[K.P_CYL_R] = ln.cylinder_radius
            P[K.P_BOX_R] = ln.cylinder_radius + margin
        P[K.P_BOX_ZLO], P[K.P_BOX_ZHI] = ln.bottom_z - margin, ln.apex_z + margin
        # A Newton step this small (relative to 1 + |t|) is rounding: the solve has converged. The
        # reference's 1e-7 is below float32 resolution (its steps then only jiggle t by an ulp).
        P[K.P_NEWTON_TOL], P[K.P_STEP_TOL] = 1e-4, (1e-6 if ft == np.float32 else 1e-12)
        P[K.P_TOP_R], P[K.P_TOP_APEX] = ln.top_radius, ln.apex_z
        P[K.P_TOP_AP2] = math.inf if ln.top_aperture is None else ln.top_aperture ** 2
        P[K.P_BOT_Z] = ln.bottom_z
        P[K.P_BOT_AP2] = math.inf if ln.bottom_aperture is None else ln.bottom_aperture ** 2
        P[K.P_PLANE_TOL], P[K.P_BODY_TOL], P[K.P_CYL_IN_TOL] = 1e-4, 1e-3, 2e-4
    F[K.F_SAMPLER] = K.SAMPLER_CODES[sampler]
    F[K.F_K] = max(1, round(math.sqrt(rays)))
    F[K.F_N] = rays
    m32 = (1 << 32) - 1
    s = int(seed)
    seeds = np.array([_splitmix(s * 4 + 1), _splitmix(s * 4 + 2) & m32, _splitmix(s * 4 + 3) & m32], dtype=np.uint64)
    return P.astype(ft), F, seeds


def grid_tables(P, F) -> np.ndarray:
    """(4, k): per-row ``cos, sin`` of the grid sampler's polar angle and per-column ``cos, sin`` of its
    azimuth, in the kernel's float type with the reference's operations (:func:`sim.optics.sampling.grid_points`,
    :func:`sim.optics.sampling.emission_directions`)."""
    from sim.optics import kernel as K

    ft = P.dtype.type
    k = int(F[K.F_K])
    c = (np.arange(k).astype(ft) + ft(0.5)) / ft(k)
    x = ft(1.0) - c * P[K.P_EM_A]
    ct = np.sqrt(x) if F[K.F_EM_SQRT] else np.power(x, P[K.P_EM_EXP])
    st = np.sqrt(np.maximum(ft(1.0) - ct * ct, ft(0.0)))
    phi = P[K.P_TWO_PI] * c
    return np.ascontiguousarray(np.stack([ct, st, np.cos(phi), np.sin(phi)]).astype(ft))


def pass_tables(layouts, dtype):
    """``(PT, PI, offsets)`` of the kernel's binning passes for ``layouts`` (see :func:`sim.optics.kernel.trace_range`):
    every (height, angle) pass of every layout, and where each layout's passes start in a slot's bins."""
    ft = float_dtype(dtype).type
    PT, PI, offsets = [], [], []
    off = 0
    for lay in layouts:
        g = lay.grid
        H, W = g.shape
        cy, cx = g.centre
        C = lay.channels
        offsets.append(off)
        for h in lay.heights:
            for a in lay.angles:
                PT.append((g.z - h, math.cos(a), math.sin(a), 1.0 / g.pitch[1], 1.0 / g.pitch[0], cx + 0.5, cy + 0.5,
                           1.0 / g.area, g.reach2))
                PI.append((H, W, C, off))
                off += H * W * C
    offsets.append(off)
    PT = np.asarray(PT, dtype=ft).reshape(-1, 9)
    PI = np.asarray(PI, dtype=np.int64).reshape(-1, 4)
    return PT, PI, offsets


def kernel_threads(threads: int | None = None) -> int:
    """Threads (and so bin slots) of the CPU kernel: ``threads``, else ``$IRISTAC_TRACE_THREADS``, else every core."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    t = threads or int(os.environ.get("IRISTAC_TRACE_THREADS", "0") or 0) or cores
    return max(1, int(t))


_POOL: list = []
_REDO = 1 << 16  # rays a slot hands to the scalar path at a time


def trace_cpu(P, F, seeds, tab, PT, PI, bins, books, counts) -> None:
    """Trace the rays ``0 .. F[F_N]-1`` of one LED on the CPU, slot ``s`` of ``bins`` (S, total),
    ``books`` (S, 4) and ``counts`` (S, 5) taking the ``s``-th contiguous range on its own thread.
    ``P, F`` are the parameter arrays (:func:`kernel_params`)."""
    from concurrent.futures import ThreadPoolExecutor

    from sim.optics import kernel as K

    Pt, Ft = K.as_tuple(P), K.as_tuple(F)
    n = int(F[K.F_N])
    S = bins.shape[0]
    per = (n + S - 1) // S

    def slot(s):
        pos, hi = min(n, s * per), min(n, (s + 1) * per)
        redo = np.empty(min(_REDO, max(hi - pos, 1) + K.BLOCK), dtype=np.int64)
        while pos < hi:
            pos, r = K.trace_range(Pt, Ft, seeds, tab, PT, PI, bins[s], books[s], counts[s], pos, hi, redo)
            if r:  # rays only the scalar path finishes (compiled when a scene first needs it)
                K.trace_redo(Pt, Ft, seeds, tab, PT, PI, bins[s], books[s], counts[s], redo, r)

    if S == 1:
        slot(0)
        return
    if not _POOL or _POOL[0]._max_workers < S:
        _POOL[:] = [ThreadPoolExecutor(S, thread_name_prefix="iristac-trace")]
    list(_POOL[0].map(slot, range(S)))


def warm_up(dtype=np.float32, device: str = "cpu") -> float:
    """Compile (or load from the disk cache) the kernel for ``dtype`` on ``device``; seconds it took
    (0 when this process has it already). Tracing calls it, so its time is never in a trace's rate."""
    ft = float_dtype(dtype)
    key = (str(ft), "cuda" if str(device).startswith("cuda") else "cpu")
    if key in _COMPILED:
        return 0.0
    t0 = time.perf_counter()
    if key[1] == "cuda":
        from sim.optics import kernel_cuda

        kernel_cuda.warm_up(ft)
    else:
        from sim.optics import kernel as K

        # No rays: compiles (or loads) trace_range; trace_redo waits until a scene needs it.
        K.trace_range(K.as_tuple(np.zeros(K.P_COUNT, dtype=ft)),
                      K.as_tuple(np.zeros(K.F_COUNT, dtype=np.int64)), np.zeros(3, np.uint64), np.zeros((4, 1), ft), np.zeros((1, 9), ft), np.zeros((1, 4), np.int64),
                      np.zeros(1, ft), np.zeros(4), np.zeros(5, np.int64), 0, 0, np.zeros(1, np.int64))
    _COMPILED[key] = time.perf_counter() - t0
    return _COMPILED[key]


def cuda_available() -> tuple[bool, str]:
    """``(ok, why not)``: whether the kernel can run on a CUDA device here (:mod:`sim.optics.kernel_cuda`)."""
    from sim.optics.kernel_cuda import cuda_available as available

    return available()


def compile_seconds() -> float:
    """Seconds this process spent compiling or loading the kernel (every float type and device)."""
    return float(sum(_COMPILED.values()))


def trace_led(scene, layouts=(), *, led: int = 0, rays: int | None = None, sampler: str | None = None,
              seed: int | None = None, dtype=None, device="cpu", refractive_index: float | None = None,
              newton_iterations: int | None = None, threads: int | None = None):
    """Trace one LED of ``scene`` with the compiled kernel and bin it on every pass of ``layouts``.

    Parameters
    ----------
    scene : sim.scene.Scene
    layouts : sequence of sim.optics.grid.BinLayout
    led, rays, sampler, seed :
        As :func:`sim.optics.tracer.trace_source` (the scene's trace defaults when None).
    dtype : float32 (default) or float64, as a name, numpy or torch dtype
    device : ``cpu`` or a CUDA device (``cuda``, ``cuda:1``): the numba.cuda kernel.
    newton_iterations : int, optional
        Cap of the swept-arc Newton solves (default 10, as the reference).
    threads : int, optional
        CPU threads (= bin slots): :func:`kernel_threads`.

    Returns
    -------
    images : list of ndarray
        Per layout, the binned passes ``(D, B, H * W, C)`` in LED 0's frame (what
        :class:`sim.optics.grid.ImageBins` holds).
    trace : SourceTrace
        Energy books, counters and time (``compile_seconds`` apart).
    """
    from sim.optics import kernel as K

    t0 = time.perf_counter()
    tr = scene.trace
    kind = sampler or tr.sampler
    n = actual_rays(int(rays if rays is not None else tr.rays), kind)
    ft = float_dtype(dtype)
    cuda = str(device).startswith("cuda")
    comp = warm_up(ft, device)
    P, F, seeds = kernel_params(scene, led=led, rays=n, sampler=kind, seed=tr.seed if seed is None else seed, dtype=ft,
                                refractive_index=refractive_index, newton_iterations=newton_iterations or 10)
    layouts = [lay if isinstance(lay, BinLayout) else lay.layout for lay in layouts]
    PT, PI, offsets = pass_tables(layouts, ft)
    tab = grid_tables(P, F) if kind == "grid" else np.zeros((4, 1), ft)
    _count_effects(scene, layouts, F)
    if cuda:
        from sim.optics import kernel_cuda

        flat, books, counts = kernel_cuda.trace(P, F, seeds, tab, PT, PI, offsets[-1], device)
        flat = flat.astype(ft, copy=False)
    else:
        S = kernel_threads(threads)
        bins = np.zeros((S, max(offsets[-1], 1)), dtype=ft)
        books = np.zeros((S, len(K.BOOKS)))
        counts = np.zeros((S, len(K.COUNTS)), dtype=np.int64)
        trace_cpu(P, F, seeds, tab, PT, PI, bins, books, counts)
        flat = bins[0] if S == 1 else bins.sum(0, dtype=ft)
    images = []
    for i, lay in enumerate(layouts):
        H, W = lay.grid.shape
        images.append(flat[offsets[i]:offsets[i + 1]].reshape(len(lay.heights), len(lay.angles), H * W, lay.channels))
    b = books.sum(0)
    c = counts.sum(0)
    lens = bool(F[K.F_LENS])
    bounces = int(F[K.F_BOUNCES])
    energy = Energy(emitted=n * (1.0 / n), on_screen=float(b[0]), elsewhere=float(b[1]), reflected=float(b[2]),
                    absorbed=float(b[3]))
    counters = {"tir_absorbed": int(c[0]) if lens and bounces == 0 else 0,
                "tir_bounces": int(c[1]), "bounce_limit": int(c[0]) if bounces else 0,
                "aperture_absorbed": int(c[2]), "numerical_lost": int(c[3]), "newton_unconverged": int(c[4])}
    return images, SourceTrace(led=led, rays=n, seconds=time.perf_counter() - t0, energy=energy, counters=counters,
                               engine="kernel", compile_seconds=comp)


def lens_rays(scene, origins, directions, *, powers=None, dtype=None, refractive_index: float | None = None,
              newton_iterations: int | None = None):
    """Given rays through ``scene``'s lens with the kernel's scalar path (:func:`sim.optics.kernel.trace_ray`).

    Parameters
    ----------
    origins, directions : array_like, shape (N, 3)
        Rays in the optical frame (unit directions); ``powers`` (N,) default 1.

    Returns
    -------
    dict of ndarray: ``origin`` (N, 3) and ``direction`` (N, 3) of the ray leaving the optics,
    ``power``, ``reflected``, ``absorbed`` (N,), ``code`` (N,) int (0 out, 1 TIR lost, 2 aperture
    stop, 3 numerical loss, 4 unconverged) and ``bounces`` (N,) int.

    Examples
    --------
    >>> from sim.scene import load_scene
    >>> r = lens_rays(load_scene("default"), [[0.0, 0.0, -5.0]], [[0.0, 0.0, 1.0]], dtype="float64")
    >>> r["direction"].round(6).tolist(), int(r["code"][0]), bool(0.9 < r["power"][0] < 1.0)
    ([[0.0, 0.0, 1.0]], 0, True)
    """
    from sim.optics import kernel as K

    ft = float_dtype(dtype)
    O = np.ascontiguousarray(np.asarray(origins, dtype=ft).reshape(-1, 3))
    D = np.ascontiguousarray(np.asarray(directions, dtype=ft).reshape(-1, 3))
    W = np.ones(len(O), dtype=ft) if powers is None else np.ascontiguousarray(np.asarray(powers, dtype=ft))
    P, F, _ = kernel_params(scene, rays=1, sampler="random", dtype=ft, refractive_index=refractive_index,
                            newton_iterations=newton_iterations or 10)
    out = np.zeros((len(O), 11), dtype=np.float64)
    K.trace_rays(K.as_tuple(P), K.as_tuple(F), O, D, W, out)
    return {"origin": out[:, 0:3], "direction": out[:, 3:6], "power": out[:, 6], "reflected": out[:, 7],
            "absorbed": out[:, 8], "code": out[:, 9].astype(int), "bounces": out[:, 10].astype(int)}


def _count_effects(scene, layouts, F):
    """What the kernel computes this call (:mod:`sim.optics.instrument`: a disabled effect never runs)."""
    from sim.optics import kernel as K

    if scene.has("emission_profile"):
        instrument.count("emission_profile")
    if F[K.F_LENS]:
        instrument.count("lens")
        if F[K.F_FRESNEL]:
            instrument.count("fresnel", int(F[K.F_BOUNCES]) + 2)
        if F[K.F_BOUNCES]:
            instrument.count("internal_bounces", int(F[K.F_BOUNCES]))
    if any(len(lay.heights) > 1 or lay.heights[0] != 0.0 for lay in layouts):
        instrument.count("depth_field")
