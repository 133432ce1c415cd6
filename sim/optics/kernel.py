"""The compiled ray kernel: one LED's rays from emission to the binned images in one pass.

Every ray goes through the same code: its square sample (the grid, a counter-based random
stream, stratified jitter or scrambled Sobol, all made here), its emission direction, the
lens (robust entry through the convex body, refraction and Fresnel at both surfaces, total
internal reflection absorbed or followed for up to K bounces, clear apertures), the energy
books (float64) and the binning of ``E`` and ``V`` on every pass of a
:class:`sim.optics.grid.BinLayout`. The physics is the eager torch tracer's
(:mod:`sim.optics.tracer`, the reference) operation for operation, so on the grid sampler the
two agree ray by ray to float rounding.

Speed comes from SIMD. Rays go in blocks of :data:`BLOCK`: a scalar loop emits them, then
branch-free loops over the block's arrays (selects, no early exits; LLVM vectorizes them,
AVX-512: 16 float32 lanes) take every ray through the lens at once: the swept-arc entry solve
as masked Newton steps of the whole block (stopping when no lane moves), then refraction in,
the swept-arc exit solve the same way (for the rays that leave through a rounded edge), the
exit surface, Snell, Fresnel and TIR, then the books and a vector loop of pixel indices per
binning pass before the scalar adds. The rays that loop cannot finish (total internal
reflection to follow, with the internal_bounces effect) go to :func:`trace_redo`, the scalar
:func:`trace_ray` built from the same functions with the full loops, compiled only when a
scene first needs it. The block loops are compiled with ``noalias`` arguments
(:data:`BLOCK_JIT`): LLVM vectorizes a loop over many arrays only when it need not check at
run time that none overlaps another.

The scene enters as two small arrays built by :func:`sim.optics.engine.kernel_params`:
``P`` (floats of the kernel's type: geometry, tolerances and constants, slots ``P_*``) and
``F`` (int64 flags and counts, slots ``F_*``). A new lens or LED parameter is a new slot here
and one line in ``kernel_params``; no signature changes. The per-ray functions are plain
``@njit`` functions, so the CUDA kernel (:mod:`sim.optics.kernel_cuda`) compiles the same code
as device functions.

CPU parallelism: :func:`sim.optics.engine.trace_led` gives each of ``S`` bin slots a contiguous
range of rays and runs :func:`trace_range` (which releases the GIL) on one thread per slot;
each slot has its own images and books (no atomics), summed at the end in slot order, so a
result is reproducible for a given slot count. (Python threads rather than ``prange``: the
same speed, and no parallel-loop machinery to compile.) Compiled once per float type and
cached on disk (``cache=True``; ``NUMBA_CACHE_DIR`` moves the cache).
Division follows IEEE (``error_model="numpy"``: no zero checks, which would also stop SIMD).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types
from numba.core.compiler import CompilerBase, DefaultPassBuilder
from numba.core.compiler_machinery import FunctionPass, register_pass
from numba.core.typed_passes import NopythonTypeInference
from numba.extending import overload

__all__ = ["P_SLOTS", "F_SLOTS", "BOOKS", "COUNTS", "SAMPLER_CODES", "BLOCK", "as_tuple", "trace_range", "trace_redo", "trace_ray", "trace_rays", "FASTMATH"]

# -- parameter slots (P: floats of the kernel's type; F: int64) --------------------------------
P_SLOTS = ("one", "src_x", "src_y", "src_z", "m00", "m01", "m02", "m10", "m11", "m12", "m20", "m21", "m22",
           "em_a", "em_exp", "two_pi", "w0", "ng", "eta_in", "box_r", "box_zlo", "box_zhi", "arc_r1", "arc_rhoc",
           "arc_zc", "arc_zlo", "arc_zhi", "newton_tol", "step_tol", "cyl_r", "top_r", "top_apex", "top_ap2",
           "bot_z", "bot_ap2", "plane_tol", "body_tol", "plane_z", "half_x", "half_y", "rho_eps", "cyl_in_tol",
           "inv_2_24", "inf")
(P_ONE, P_SRC_X, P_SRC_Y, P_SRC_Z, P_M00, P_M01, P_M02, P_M10, P_M11, P_M12, P_M20, P_M21, P_M22,
 P_EM_A, P_EM_EXP, P_TWO_PI, P_W0, P_NG, P_ETA_IN, P_BOX_R, P_BOX_ZLO, P_BOX_ZHI, P_ARC_R1, P_ARC_RHOC,
 P_ARC_ZC, P_ARC_ZLO, P_ARC_ZHI, P_NEWTON_TOL, P_STEP_TOL, P_CYL_R, P_TOP_R, P_TOP_APEX, P_TOP_AP2,
 P_BOT_Z, P_BOT_AP2, P_PLANE_TOL, P_BODY_TOL, P_PLANE_Z, P_HALF_X, P_HALF_Y, P_RHO_EPS, P_CYL_IN_TOL,
 P_INV_2_24, P_INF) = range(44)
P_COUNT = 44

F_SLOTS = ("lens", "arc", "fresnel", "bounces", "iterations", "em_sqrt", "sampler", "k", "n")
F_LENS, F_ARC, F_FRESNEL, F_BOUNCES, F_ITERATIONS, F_EM_SQRT, F_SAMPLER, F_K, F_N = range(9)
F_COUNT = 9

SAMPLER_CODES = {"grid": 0, "random": 1, "stratified": 2, "sobol": 3}
# Energy books (float64 per slot) and counters (int64 per slot), in this order.
BOOKS = ("on_screen", "elsewhere", "reflected", "absorbed")
COUNTS = ("tir_lost", "tir_bounces", "aperture_absorbed", "numerical_lost", "newton_unconverged")
# Ray fates (codes): what the books and counters record.
OUT, TIR_LOST, STOPPED, LOST, UNCONVERGED, REDO = 0, 1, 2, 3, 4, 5

SIDE, TOP, BOTTOM = 0, 1, 2

# Rays per block: the block's arrays stay in the L1 cache.
BLOCK = 256

# fastmath without "nnan"/"ninf": the lens code uses +-inf as "no intersection" (both flags
# would let LLVM delete those tests). Contraction (FMA) and reciprocal division are allowed
# (measured ~10 % faster). The per-ray functions are forced inline at the LLVM level
# (forceinline): every call in a block loop must be inlined for the loop to vectorize, and
# numba's own IR inlining (inline="always") compiled 25 % slower for the same code.
FASTMATH = {"contract", "arcp", "nsz"}
JIT = dict(fastmath=FASTMATH, error_model="numpy")


INLINE = dict(JIT, forceinline=True)



@register_pass(mutates_CFG=False, analysis_only=True)
class _NoAlias(FunctionPass):
    """Marks the compiled function's pointer arguments ``noalias`` (numba's flag, not an option of ``@njit``)."""

    _name = "iristac_noalias"

    def __init__(self):
        FunctionPass.__init__(self)

    def run_pass(self, state):
        state.flags.noalias = True
        return False


class _NoAliasCompiler(CompilerBase):
    """numba's nopython pipeline with :class:`_NoAlias` before lowering."""

    def define_pipelines(self):
        pm = DefaultPassBuilder.define_nopython_pipeline(self.state)
        pm.add_pass_after(_NoAlias, NopythonTypeInference)
        pm.finalize()
        return [pm]


# The block loops (``_block_*``): their array arguments never overlap (each is its own
# np.empty of trace_range; never one array passed twice), and saying so lets LLVM vectorize a
# loop over many arrays: without it each pair needs a run-time overlap check, and past a few
# dozen LLVM gives up ("too many memory checks") and the loop runs scalar (3x slower lens).
BLOCK_JIT = dict(JIT, pipeline_class=_NoAliasCompiler)

_M32 = np.uint64(0xFFFFFFFF)


def as_tuple(a) -> tuple:
    """A parameter array (``P`` or ``F``) as the tuple the compiled functions take: typed scalars,
    kept in registers rather than in memory the compiler must assume a store may change."""
    return tuple(a.dtype.type(x) for x in a)


# -- the float type follows P ------------------------------------------------------------------
def _fl(x, like):  # pragma: no cover - replaced by the overload in compiled code
    return float(x)


@overload(_fl, inline="always")
def _fl_overload(x, like):
    """``x`` converted to the float type of ``like`` (numba promotes int op float32 to float64)."""
    if like == types.float32:
        return lambda x, like: np.float32(x)
    return lambda x, like: np.float64(x)


# -- samplers ----------------------------------------------------------------------------------
@njit(**INLINE)
def _mix64(z):
    """splitmix64's finaliser: a counter-based stream (the same numbers for any chunking or threads)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(**INLINE)
def _rev32(x):
    """Bit reversal of the low 32 bits of a uint64."""
    x = ((x >> np.uint64(1)) & np.uint64(0x55555555)) | ((x & np.uint64(0x55555555)) << np.uint64(1))
    x = ((x >> np.uint64(2)) & np.uint64(0x33333333)) | ((x & np.uint64(0x33333333)) << np.uint64(2))
    x = ((x >> np.uint64(4)) & np.uint64(0x0F0F0F0F)) | ((x & np.uint64(0x0F0F0F0F)) << np.uint64(4))
    x = ((x >> np.uint64(8)) & np.uint64(0x00FF00FF)) | ((x & np.uint64(0x00FF00FF)) << np.uint64(8))
    return ((x >> np.uint64(16)) | (x << np.uint64(16))) & _M32


@njit(**INLINE)
def _owen(x, seed):
    """Nested uniform (Owen) scrambling of a 32-bit Sobol value (Laine-Karras hash, Burley 2020)."""
    x = _rev32(x)
    x = (x + seed) & _M32
    x ^= (x * np.uint64(0x6C50B47C)) & _M32
    x ^= (x * np.uint64(0xB82F1E52)) & _M32
    x ^= (x * np.uint64(0xC7AFE638)) & _M32
    x ^= (x * np.uint64(0x8D22F6E6)) & _M32
    return _rev32(x)


@njit(**INLINE)
def _unit24(bits, P):
    """The top 24 of 32 bits as a float in [0, 1): exact in float32 and float64, never 1."""
    return _fl(bits >> np.uint64(8), P[P_ONE]) * P[P_INV_2_24]


@njit(**INLINE)
def sample(P, F, seeds, n):
    """Square sample ``(u, v)`` of ray ``n`` (int64) for the sampler ``F[F_SAMPLER]``.

    grid: the cell centres of the ``k x k`` grid, exactly the reference's
    :func:`sim.optics.sampling.grid_points`; random: a counter-based hash of ``(seed, n)``;
    stratified: one hashed jitter per grid cell; sobol: the first two Sobol dimensions with
    Owen scrambling seeded by ``seeds[1:3]``.
    """
    one = P[P_ONE]
    half = one / (one + one)
    kind = F[F_SAMPLER]
    if kind == 1:
        h = _mix64(seeds[0] + np.uint64(n) * np.uint64(0x9E3779B97F4A7C15))
        return _unit24(h & _M32, P), _unit24(h >> np.uint64(32), P)
    if kind == 3:
        nn = np.uint64(n)
        x = _rev32(nn)
        y = np.uint64(0)
        v = np.uint64(0x80000000)
        b = nn
        while b:
            if b & np.uint64(1):
                y ^= v
            v ^= v >> np.uint64(1)
            b >>= np.uint64(1)
        return _unit24(_owen(x, seeds[1]), P), _unit24(_owen(y, seeds[2]), P)
    k = F[F_K]
    i = n // k
    j = n - i * k
    kf = _fl(k, one)
    if kind == 2:
        h = _mix64(seeds[0] + np.uint64(n) * np.uint64(0x9E3779B97F4A7C15))
        return (_fl(i, one) + _unit24(h & _M32, P)) / kf, (_fl(j, one) + _unit24(h >> np.uint64(32), P)) / kf
    return (_fl(i, one) + half) / kf, (_fl(j, one) + half) / kf


# -- emission ----------------------------------------------------------------------------------
@njit(**INLINE)
def polar(P, F, u):
    """``(cos, sin)`` of the polar angle of sample ``u``: the inverse CDF of ``cos^m sin`` on the cone."""
    one = P[P_ONE]
    x = one - u * P[P_EM_A]
    ct = math.sqrt(x) if F[F_EM_SQRT] else x ** P[P_EM_EXP]
    return ct, math.sqrt(max(one - ct * ct, one - one))


@njit(**INLINE)
def azimuth(P, v):
    phi = P[P_TWO_PI] * v
    return math.cos(phi), math.sin(phi)


@njit(**INLINE)
def direction(P, ct, st, cp, sp):
    """World direction of the local ``(st cp, st sp, ct)`` (the LED frame turned by its azimuth)."""
    lx = st * cp
    ly = st * sp
    return (lx * P[P_M00] + ly * P[P_M01] + ct * P[P_M02], lx * P[P_M10] + ly * P[P_M11] + ct * P[P_M12],
            lx * P[P_M20] + ly * P[P_M21] + ct * P[P_M22])


@njit(**INLINE)
def emit(P, F, seeds, tab, n):
    """Unit direction of ray ``n`` (the origin is the LED, ``P[P_SRC_*]``); the grid reads ``tab``."""
    if F[F_SAMPLER] == 0:
        k = F[F_K]
        i = n // k
        j = n - i * k
        return direction(P, tab[0, i], tab[1, i], tab[2, j], tab[3, j])
    u, v = sample(P, F, seeds, n)
    ct, st = polar(P, F, u)
    cp, sp = azimuth(P, v)
    return direction(P, ct, st, cp, sp)


# -- geometry (branch-free: selects, so that the block loop vectorizes) -------------------------
@njit(**INLINE)
def _quadratic(a, b, c, one):
    """Roots ``t1 <= t2`` of ``a t^2 + 2 b t + c`` (cancellation-free; 0 where not real) and ``real``."""
    zero = one - one
    disc = b * b - a * c
    real = (disc >= zero) & (a > zero)
    sq = math.sqrt(max(disc, zero))
    q = -(b + (sq if b >= zero else -sq))
    r1 = q / (a if real else one)
    r2 = (c / (q if q != zero else one)) if q != zero else zero
    t1 = min(r1, r2)
    t2 = max(r1, r2)
    return (t1 if real else zero), (t2 if real else zero), real


@njit(**INLINE)
def box(P, ox, oy, oz, dx, dy, dz):
    """``(t_lo, t_hi)`` inside the lens's bounding cylinder (``t_lo >= 0``); empty when ``t_lo > t_hi``."""
    one = P[P_ONE]
    zero = one - one
    R = P[P_BOX_R]
    a = dx * dx + dy * dy
    c = ox * ox + oy * oy - R * R
    t1, t2, real = _quadratic(a, ox * dx + oy * dy, c, one)
    wide = (a == zero) & (c <= zero)  # parallel to the axis, inside the cylinder
    c_lo = t1 if real else (-P[P_INF] if wide else P[P_INF])
    c_hi = t2 if real else (P[P_INF] if wide else -P[P_INF])
    zlo, zhi = P[P_BOX_ZLO], P[P_BOX_ZHI]
    flat = dz == zero
    in_slab = (oz >= zlo) & (oz <= zhi)
    sdz = one if flat else dz
    s1 = (zlo - oz) / sdz
    s2 = (zhi - oz) / sdz
    s_lo = (-P[P_INF] if in_slab else P[P_INF]) if flat else min(s1, s2)
    s_hi = (P[P_INF] if in_slab else -P[P_INF]) if flat else max(s1, s2)
    return max(max(c_lo, s_lo), zero), min(c_hi, s_hi)


@njit(**INLINE)
def arc_parts(P, ox, oy, oz, dx, dy, dz, t):
    """``(Sn, dSn, rho, s)`` of the swept arc at ``o + t d`` (see :class:`sim.optics.torus.SweptArc`):
    ``S = Sn / s`` and ``S' = dSn / (rho s)`` with ``s, rho > 0``, so a Newton step is ``Sn rho / dSn``."""
    x = ox + t * dx
    y = oy + t * dy
    z = oz + t * dz
    rho = max(math.sqrt(x * x + y * y), P[P_RHO_EPS])
    zq = min(max(z, P[P_ARC_ZLO]), P[P_ARC_ZHI])
    u = zq - P[P_ARC_ZC]
    r1 = P[P_ARC_R1]
    s = math.sqrt(r1 * r1 - u * u)
    sn = (rho - P[P_ARC_RHOC] - s) * s + u * (z - zq)
    dsn = (x * dx + y * dy) * s + u * dz * rho
    return sn, dsn, rho, s


@njit(**INLINE)
def newton_step(P, ox, oy, oz, dx, dy, dz, t, sn, dsn, rho, s, active, dead, left):
    """One masked step of the monotone Newton on the convex ``S`` (left: toward the first root, else
    the last). A lane stops at ``S <= 0``, when the slope points away (``dead``: no root on that
    side) or when its next step would be within rounding (converged: judged from the new slope, so
    no step is spent finding that out). Returns the new ``(t, sn, dsn, rho, s, active, dead)``."""
    zero = P[P_ONE] - P[P_ONE]
    active = active & (sn > zero)
    away = (dsn >= zero) if left else (dsn <= zero)
    dead = dead | (active & away)
    active = active & (not away)
    step = sn * rho / (dsn if active else P[P_ONE])
    t = (t - step) if active else t
    sn, dsn, rho, s = arc_parts(P, ox, oy, oz, dx, dy, dz, t)
    nxt = sn * rho / (dsn if dsn != zero else P[P_ONE])
    active = active & (abs(nxt) > P[P_STEP_TOL] * (P[P_ONE] + abs(t)))
    return t, sn, dsn, rho, s, active, dead


@njit(**INLINE)
def arc_value(P, x, y, z):
    """``S = rho - g(z)`` with ``g`` extended by its tangent lines beyond the arc's z range."""
    zq = min(max(z, P[P_ARC_ZLO]), P[P_ARC_ZHI])
    u = zq - P[P_ARC_ZC]
    r1 = P[P_ARC_R1]
    s = math.sqrt(r1 * r1 - u * u)
    return math.sqrt(x * x + y * y) - (P[P_ARC_RHOC] + s - u / s * (z - zq))


@njit(**INLINE)
def top_roots(P, ox, oy, oz, dx, dy, dz):
    """The top ball's roots along a ray, relative to the apex (float32 keeps ``R = 600`` mm accurate)."""
    oz = oz - P[P_TOP_APEX]
    R = P[P_TOP_R]
    b = ox * dx + oy * dy + oz * dz + R * dz
    c = ox * ox + oy * oy + oz * oz + (R + R) * oz
    one = _fl(1, P[P_ONE])  # a constant: the root q / a with a = 1 costs no division
    return _quadratic(one, b, c, one)


@njit(**INLINE)
def cyl_roots(P, ox, oy, dx, dy):
    R = P[P_CYL_R]
    c = ox * ox + oy * oy - R * R
    t1, t2, real = _quadratic(dx * dx + dy * dy, ox * dx + oy * dy, c, P[P_ONE])
    return t1, t2, real, c <= P[P_CYL_IN_TOL] * R


@njit(**INLINE)
def side_entry_start(P, F, ox, oy, oz, dx, dy, dz):
    """The box and the swept-arc solve's start: ``(t_lo, t_hi, t, sn, dsn, rho, s, active, inside)``."""
    t_lo, t_hi = box(P, ox, oy, oz, dx, dy, dz)
    sn, dsn, rho, s = arc_parts(P, ox, oy, oz, dx, dy, dz, t_lo)
    zero = P[P_ONE] - P[P_ONE]
    return t_lo, t_hi, t_lo, sn, dsn, rho, s, (t_lo <= t_hi) & (sn > zero), sn <= zero


@njit(**INLINE)
def side_entry_end(P, t_hi, t, sn, dsn, s, dead, inside):
    """``(e0, unconverged)``: the side set's entry ``t`` (``-inf`` when the ray starts inside it, ``+inf``
    when it misses) after the Newton steps, as :meth:`sim.optics.torus.SweptArc.entry_capped`."""
    zero = P[P_ONE] - P[P_ONE]
    S = sn / s
    ahead = (not dead) & (not inside) & (t <= t_hi)
    hit = ahead & (S <= P[P_NEWTON_TOL])
    e0 = -P[P_INF] if inside else (t if hit else P[P_INF])
    return e0, ahead & (S > P[P_NEWTON_TOL]) & (dsn < zero)


@njit(**INLINE)
def enter_rest(P, F, ox, oy, oz, dx, dy, dz, boxok, e0):
    """Given the side set's entry ``e0``: ``(t, surface, hit)`` of the lens (:meth:`sim.optics.lens.LensBody.enter`)."""
    one = P[P_ONE]
    zero = one - one
    if not F[F_ARC]:
        c1, _, real, cin = cyl_roots(P, ox, oy, dx, dy)
        e0 = c1 if real else (-P[P_INF] if cin else P[P_INF])
    t1, _, real = top_roots(P, ox, oy, oz, dx, dy, dz)
    e1 = t1 if real else P[P_INF]
    sdz = dz if dz > zero else one
    e2 = ((P[P_BOT_Z] - oz) / sdz) if dz > zero else (-P[P_INF] if oz >= P[P_BOT_Z] - P[P_PLANE_TOL] else P[P_INF])
    t = max(max(e0, e1), e2)
    sid = SIDE if e0 >= max(e1, e2) else (TOP if e1 >= e2 else BOTTOM)
    hit = boxok & (t > zero) & (t < P[P_INF])
    ts = t if hit else zero
    x, y, z = ox + ts * dx, oy + ts * dy, oz + ts * dz
    tol = P[P_BODY_TOL]
    in_side = (arc_value(P, x, y, z) <= tol) if F[F_ARC] else (math.sqrt(x * x + y * y) <= P[P_CYL_R] + tol)
    zt = z - P[P_TOP_APEX]
    R2 = P[P_TOP_R] + P[P_TOP_R]
    in_top = x * x + y * y + zt * zt + R2 * zt <= R2 * tol
    hit = hit & in_side & in_top & (z >= P[P_BOT_Z] - tol)
    return (t if hit else zero), sid, hit


@njit(**INLINE)
def leave_start(P, F, ox, oy, oz, dx, dy, dz):
    """Exits of a ray inside the lens other than the side's: ``(x1, x2, x12, t_lo, t_hi, x0)``, with
    ``x0`` the cylinder's exit, or for a swept arc ``+inf`` (its solve starts at ``min(t_hi, x12)``)."""
    zero = P[P_ONE] - P[P_ONE]
    _, t2, real = top_roots(P, ox, oy, oz, dx, dy, dz)
    x1 = t2 if real else -P[P_INF]
    sdz = dz if dz < zero else P[P_ONE]
    x2 = ((P[P_BOT_Z] - oz) / sdz) if dz < zero else (
        P[P_INF] if ((oz >= P[P_BOT_Z] - P[P_PLANE_TOL]) | (dz > zero)) else -P[P_INF])
    x12 = min(x1, x2)
    t_lo, t_hi = box(P, ox, oy, oz, dx, dy, dz)
    x0 = P[P_INF]
    if not F[F_ARC]:
        _, c2, real, cin = cyl_roots(P, ox, oy, dx, dy)
        x0 = c2 if real else (P[P_INF] if cin else -P[P_INF])
    return x1, x2, x12, t_lo, t_hi, x0


@njit(**INLINE)
def leave_end(P, x0, x1, x2, x12):
    """``(t, surface, good)`` of the exit from the side's ``x0`` and the others' (:meth:`sim.optics.lens.LensBody.leave`)."""
    zero = P[P_ONE] - P[P_ONE]
    t = min(x0, x12)
    sid = SIDE if x0 <= x12 else (TOP if x1 <= x2 else BOTTOM)
    good = (t >= zero) & (t < P[P_INF])
    return (t if good else zero), sid, good


@njit(**INLINE)
def normal(P, F, x, y, z, sid):
    """Outward unit normal of surface ``sid`` at ``(x, y, z)`` (every surface's, then selected)."""
    one = P[P_ONE]
    zero = one - one
    inv = one / P[P_TOP_R]
    tx, ty, tz = x * inv, y * inv, (z - P[P_TOP_APEX] + P[P_TOP_R]) * inv
    rho = max(math.sqrt(x * x + y * y), P[P_RHO_EPS])
    zq = min(max(z, P[P_ARC_ZLO]), P[P_ARC_ZHI])
    u = zq - P[P_ARC_ZC]
    r1 = P[P_ARC_R1]
    nz = (u / math.sqrt(r1 * r1 - u * u)) if F[F_ARC] else zero  # -slope of g; 0 on a cylinder
    sc = one / (rho * math.sqrt(one + nz * nz))
    sx, sy, sz = x * sc, y * sc, nz * rho * sc
    top = sid == TOP
    bot = sid == BOTTOM
    return ((tx if top else (zero if bot else sx)), (ty if top else (zero if bot else sy)),
            (tz if top else (-one if bot else sz)))


@njit(**INLINE)
def refract(dx, dy, dz, nx, ny, nz, eta, one):
    """Vector Snell's law at a normal on the incident side: ``(tx, ty, tz, cos_i, cos_t, tir)``."""
    ci = -(dx * nx + dy * ny + dz * nz)
    s2 = eta * eta * max(one - ci * ci, one - one)
    ct = math.sqrt(max(one - s2, one - one))
    k = eta * ci - ct
    return eta * dx + k * nx, eta * dy + k * ny, eta * dz + k * nz, ci, ct, s2 > one


@njit(**INLINE)
def fresnel(ci, ct, n1, n2, one):
    """Unpolarized Fresnel power transmittance (:func:`sim.optics.interface.fresnel_transmittance`)."""
    zero = one - one
    a, b, c, e = n1 * ci, n2 * ct, n2 * ci, n1 * ct
    ok = (a + b > zero) & (c + e > zero) & (ct > zero)
    rs = (a - b) / (a + b if ok else one)
    rp = (c - e) / (c + e if ok else one)
    T = one - (rs * rs + rp * rp) / (one + one)
    return min(max(T, zero), one) if ok else zero


@njit(**INLINE)
def stopped(P, x, y, sid):
    """Crossing the top or bottom outside its clear aperture (a housing stop)."""
    r2 = x * x + y * y
    return ((sid == TOP) & (r2 > P[P_TOP_AP2])) | ((sid == BOTTOM) & (r2 > P[P_BOT_AP2]))


@njit(**INLINE)
def cross_in(P, F, ox, oy, oz, dx, dy, dz, t, sid, w):
    """Refraction into the lens at ``o + t d``: ``(px, py, pz, dx, dy, dz, w_in, reflected, stop)``."""
    one = P[P_ONE]
    px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
    nx, ny, nz = normal(P, F, px, py, pz, sid)
    tx, ty, tz, ci, ct, _ = refract(dx, dy, dz, nx, ny, nz, P[P_ETA_IN], one)
    T = fresnel(ci, ct, one, P[P_NG], one) if F[F_FRESNEL] else one
    return px, py, pz, tx, ty, tz, w * T, w * (one - T), stopped(P, px, py, sid)


@njit(**INLINE)
def cross_out(P, F, px, py, pz, dx, dy, dz, t, sid):
    """Leaving the lens at ``p + t d``: ``(qx, qy, qz, tx, ty, tz, T, tir, stop, nx, ny, nz)`` (outward normal)."""
    one = P[P_ONE]
    qx, qy, qz = px + t * dx, py + t * dy, pz + t * dz
    nx, ny, nz = normal(P, F, qx, qy, qz, sid)
    tx, ty, tz, ci, ct, tir = refract(dx, dy, dz, -nx, -ny, -nz, P[P_NG], one)
    T = fresnel(ci, ct, P[P_NG], one, one) if F[F_FRESNEL] else one
    return qx, qy, qz, tx, ty, tz, T, tir, stopped(P, qx, qy, sid), nx, ny, nz


# -- one ray, scalar (the reference's semantics with its full loops) ---------------------------
@njit(**JIT)
def trace_ray(P, F, ox, oy, oz, dx, dy, dz, w):  # noqa: C901 - compiled: the loop body stays one function so Numba vectorises it
    """One ray from the LED through the lens.

    Returns ``(ox, oy, oz, dx, dy, dz, w, reflected, absorbed, code, bounces)``: the ray leaving
    the optics (unchanged if it misses the lens, ``w = 0`` if absorbed), the power reflected and
    absorbed on the way, its fate ``code`` (:data:`OUT`, :data:`TIR_LOST`, :data:`STOPPED`,
    :data:`LOST` or :data:`UNCONVERGED`) and the TIR bounces it took.
    """
    one = P[P_ONE]
    zero = one - one
    unconv = False
    t_lo, t_hi = box(P, ox, oy, oz, dx, dy, dz)
    boxok = t_lo <= t_hi
    e0 = P[P_INF]
    if boxok and F[F_ARC]:
        t_lo, t_hi, t, sn, dsn, rho, s, active, inside = side_entry_start(P, F, ox, oy, oz, dx, dy, dz)
        dead = False
        for _ in range(F[F_ITERATIONS]):
            if not active:
                break
            t, sn, dsn, rho, s, active, dead = newton_step(P, ox, oy, oz, dx, dy, dz, t, sn, dsn, rho, s, active,
                                                           dead, True)
        e0, unconv = side_entry_end(P, t_hi, t, sn, dsn, s, dead, inside)
    t, sid, hit = enter_rest(P, F, ox, oy, oz, dx, dy, dz, boxok, e0)
    if not hit:
        return ox, oy, oz, dx, dy, dz, w, zero, zero, (UNCONVERGED if unconv else OUT), 0
    w_led = w
    px, py, pz, dx, dy, dz, w, reflected, stop = cross_in(P, F, ox, oy, oz, dx, dy, dz, t, sid, w)
    if stop:
        return ox, oy, oz, dx, dy, dz, zero, zero, w_led, STOPPED, 0
    bounces = F[F_BOUNCES]
    for b in range(bounces + 1):
        x1, x2, x12, t_lo, t_hi, x0 = leave_start(P, F, px, py, pz, dx, dy, dz)
        if F[F_ARC]:
            t0 = min(t_hi, x12)
            sn, dsn, rho, s = arc_parts(P, px, py, pz, dx, dy, dz, t0)
            if sn > zero and t_lo <= t_hi:
                active = True
                dead = False
                for _ in range(F[F_ITERATIONS]):
                    if not active:
                        break
                    t0, sn, dsn, rho, s, active, dead = newton_step(P, px, py, pz, dx, dy, dz, t0, sn, dsn, rho,
                                                                    s, active, dead, False)
                if not dead and sn / s <= P[P_NEWTON_TOL]:
                    x0 = t0
        t, sid, good = leave_end(P, x0, x1, x2, x12)
        if not good:
            return px, py, pz, dx, dy, dz, zero, reflected, w, LOST, b
        qx, qy, qz, tx, ty, tz, T, tir, stop, nx, ny, nz = cross_out(P, F, px, py, pz, dx, dy, dz, t, sid)
        if stop:
            return qx, qy, qz, dx, dy, dz, zero, reflected, w, STOPPED, b
        if not tir:
            return qx, qy, qz, tx, ty, tz, w * T, reflected + w * (one - T), zero, OUT, b
        if b == bounces:
            return qx, qy, qz, dx, dy, dz, zero, reflected, w, TIR_LOST, b
        # Total internal reflection, followed: mirror about the normal.
        c2 = dx * nx + dy * ny + dz * nz
        c2 = c2 + c2
        dx, dy, dz = dx - c2 * nx, dy - c2 * ny, dz - c2 * nz
        px, py, pz = qx, qy, qz
    return px, py, pz, dx, dy, dz, zero, reflected, w, TIR_LOST, bounces  # not reached


# -- a block of rays, vectorized ----------------------------------------------------------------
@njit(**BLOCK_JIT)
def _block_emit(P, F, seeds, tab, start, m, EX, EY, EZ):
    """Directions of rays ``start .. start+m-1`` (scalar: table reads or hashing and trigonometry).

    The grid's row and column step along (as :func:`emit`'s, without its integer division per ray)."""
    if F[F_SAMPLER] == 0:
        k = F[F_K]
        a = start // k
        b = start - a * k
        for i in range(m):
            EX[i], EY[i], EZ[i] = direction(P, tab[0, a], tab[1, a], tab[2, b], tab[3, b])
            b += 1
            if b == k:
                a += 1
                b = 0
    else:
        for i in range(m):
            EX[i], EY[i], EZ[i] = emit(P, F, seeds, tab, start + i)


@njit(**BLOCK_JIT)
def _block_start(P, F, m, EX, EY, EZ, T, SN, DSN, RHO, S, ACT, DEAD, THI, INS, BOX):
    """The box and the swept-arc entry solve's start of each ray of a block (a vector loop);
    returns how many rays need the solve."""
    ox, oy, oz = P[P_SRC_X], P[P_SRC_Y], P[P_SRC_Z]
    arc = F[F_ARC] != 0
    need = 0
    for i in range(m):
        t_lo, t_hi, t, sn, dsn, rho, s, active, inside = side_entry_start(P, F, ox, oy, oz, EX[i], EY[i], EZ[i])
        active = active & arc
        T[i], SN[i], DSN[i], RHO[i], S[i], THI[i] = t, sn, dsn, rho, s, t_hi
        ACT[i], DEAD[i], INS[i], BOX[i] = active, False, inside, t_lo <= t_hi
        need += active
    return need


def _at(a, i):  # pragma: no cover - replaced by the overload in compiled code
    return a[i] if isinstance(a, np.ndarray) else a


@overload(_at, inline="always")
def _at_overload(a, i):
    """``a[i]`` for an array, ``a`` for a scalar (a solve's origins: each ray's, or the LED for all)."""
    if isinstance(a, types.Array):
        return lambda a, i: a[i]
    return lambda a, i: a


@njit(**BLOCK_JIT)
def _block_newton(P, left, m, OX, OY, OZ, DX, DY, DZ, T, SN, DSN, RHO, S, ACT, DEAD):
    """One masked Newton step of every ray of a block toward its first (``left``) or last root of the
    swept arc (a vector loop); returns how many still move. ``OX, OY, OZ``: origin arrays, or one
    origin for all (the LED's)."""
    moving = 0
    for i in range(m):
        t, sn, dsn, rho, s, active, dead = newton_step(P, _at(OX, i), _at(OY, i), _at(OZ, i), DX[i], DY[i], DZ[i],
                                                       T[i], SN[i], DSN[i], RHO[i], S[i], ACT[i], DEAD[i], left)
        T[i], SN[i], DSN[i], RHO[i], S[i], ACT[i], DEAD[i] = t, sn, dsn, rho, s, active, dead
        moving += active
    return moving


@njit(**JIT)
def _solve(P, F, left, m, OX, OY, OZ, DX, DY, DZ, T, SN, DSN, RHO, S, ACT, DEAD):
    """The swept-arc solves of a block: every ray stepped together, masked, until none moves.

    Masking the whole block beat packing the rays that need a solve to the front first (a
    scalar gather; measured slower on both shipped scenes, where from 1 % to 38 % of the rays
    need one)."""
    for _ in range(F[F_ITERATIONS]):
        if not _block_newton(P, left, m, OX, OY, OZ, DX, DY, DZ, T, SN, DSN, RHO, S, ACT, DEAD):
            break


@njit(**BLOCK_JIT)
def _block_entry(P, m, T, SN, DSN, S, DEAD, THI, INS, E0, UNC):
    """The side set's entry ``E0`` (and ``UNC``: unconverged) of each ray after the solve (a vector loop)."""
    for i in range(m):
        E0[i], UNC[i] = side_entry_end(P, THI[i], T[i], SN[i], DSN[i], S[i], DEAD[i], INS[i])


@njit(**BLOCK_JIT)
def _block_inside(P, F, m, EX, EY, EZ, E0, BOX, HIT, STOP, PX, PY, PZ, IX, IY, IZ, WI, RF, X1, X2, X12, X0,
                  T, SN, DSN, RHO, S, SEL, ACT, DEAD):
    """Into the lens and the start of the way out, every ray of a block (a vector loop), after the entry solve.

    Writes whether the ray enters (``HIT``) or is stopped there (``STOP``), the point ``P*`` and
    direction ``I*`` inside, the power ``WI`` inside and ``RF`` reflected, the exits through the
    top and bottom (``X1, X2, X12``; ``X0`` the cylinder side's), and the start of the swept-arc
    exit solve (``T .. S``; ``SEL`` and ``ACT`` for the rays that need it: a ray whose solve would start
    outside the side set leaves through the side). Returns how many need the solve.
    """
    one = P[P_ONE]
    zero = one - one
    ox, oy, oz = P[P_SRC_X], P[P_SRC_Y], P[P_SRC_Z]
    w0 = P[P_W0]
    arc = F[F_ARC] != 0
    need = 0
    for i in range(m):
        dx, dy, dz = EX[i], EY[i], EZ[i]
        t, sid, hit = enter_rest(P, F, ox, oy, oz, dx, dy, dz, BOX[i], E0[i])
        px, py, pz, ex, ey, ez, w_in, refl, stop_in = cross_in(P, F, ox, oy, oz, dx, dy, dz, t, sid, w0)
        x1, x2, x12, l_lo, l_hi, x0 = leave_start(P, F, px, py, pz, ex, ey, ez)
        t0 = min(l_hi, x12)
        sn, dsn, rho, s = arc_parts(P, px, py, pz, ex, ey, ez, t0)
        sel = hit & (not stop_in) & arc & (sn > zero) & (l_lo <= l_hi)
        HIT[i], STOP[i] = hit, stop_in
        PX[i], PY[i], PZ[i], IX[i], IY[i], IZ[i], WI[i], RF[i] = px, py, pz, ex, ey, ez, w_in, refl
        X1[i], X2[i], X12[i], X0[i] = x1, x2, x12, x0
        T[i], SN[i], DSN[i], RHO[i], S[i], SEL[i], ACT[i], DEAD[i] = t0, sn, dsn, rho, s, sel, sel, False
        need += sel
    return need


@njit(**BLOCK_JIT)
def _block_exit(P, F, m, EX, EY, EZ, UNC, HIT, STOP, PX, PY, PZ, IX, IY, IZ, WI, RF, X1, X2, X12, X0,
                T, SN, S, SEL, DEAD, OX, OY, OZ, DX, DY, DZ, W, AB, CODE):
    """Out of the lens, every ray of a block, branch-free (a vector loop), after the exit solve.

    Writes the ray leaving the optics (``OX .. DZ``, ``W``; only rays with power left need a
    path), the power reflected ``RF`` (added to) and absorbed ``AB`` and the fate ``CODE``;
    :data:`REDO` marks the rays only :func:`trace_ray` can finish (total internal reflection to
    follow, with the internal_bounces effect).
    """
    one = P[P_ONE]
    zero = one - one
    ox, oy, oz = P[P_SRC_X], P[P_SRC_Y], P[P_SRC_Z]
    w0 = P[P_W0]
    tol = P[P_NEWTON_TOL]
    follow = F[F_BOUNCES] > 0
    for i in range(m):
        hit, stop_in, w_in, refl = HIT[i], STOP[i], WI[i], RF[i]
        solved = SEL[i] & (not DEAD[i]) & (SN[i] / S[i] <= tol)
        t2, sid2, good = leave_end(P, T[i] if solved else X0[i], X1[i], X2[i], X12[i])
        qx, qy, qz, tx, ty, tz, T2, tir, stop_out, _, _, _ = cross_out(P, F, PX[i], PY[i], PZ[i], IX[i], IY[i],
                                                                      IZ[i], t2, sid2)
        inside_lens = hit & (not stop_in)
        out = inside_lens & good & (not stop_out)
        leaves = out & (not tir)
        OX[i] = qx if leaves else ox
        OY[i] = qy if leaves else oy
        OZ[i] = qz if leaves else oz
        DX[i] = tx if leaves else EX[i]
        DY[i] = ty if leaves else EY[i]
        DZ[i] = tz if leaves else EZ[i]
        W[i] = (w_in * T2) if leaves else (w0 if not hit else zero)
        RF[i] = (refl + w_in * (one - T2)) if leaves else (refl if inside_lens else zero)
        AB[i] = zero if (leaves | (not hit)) else (w0 if stop_in else w_in)
        code = OUT if (leaves | (not hit)) else (STOPPED if stop_in else (LOST if not good else (
            STOPPED if stop_out else TIR_LOST)))
        code = (UNCONVERGED if UNC[i] else OUT) if not hit else code
        CODE[i] = REDO if (out & tir & follow) else code


@njit(**INLINE)
def on_screen(P, ox, oy, oz, dx, dy, dz):
    """Whether a ray leaving the optics crosses the scene's imaging plane inside its rectangle."""
    zero = P[P_ONE] - P[P_ONE]
    t = (P[P_PLANE_Z] - oz) / dz
    x = ox + t * dx
    y = oy + t * dy
    return (dz != zero) & (t > zero) & (abs(x) <= P[P_HALF_X]) & (abs(y) <= P[P_HALF_Y])


@njit(**BLOCK_JIT)
def _block_books(P, m, OX, OY, OZ, DX, DY, DZ, W, RF, AB, CODE, ON, books, cnt):
    """Energy books (float64) and fate counts of a block: which rays land on the screen in a vector
    loop (``ON``), then the sums with selects, not branches (a ray lands or not at random)."""
    for i in range(m):
        ON[i] = on_screen(P, OX[i], OY[i], OZ[i], DX[i], DY[i], DZ[i])
    on = 0.0
    off = 0.0
    rf = 0.0
    ab = 0.0
    for i in range(m):
        cnt[CODE[i]] += 1
        rf += RF[i]
        ab += AB[i]
        w = W[i]
        z = w - w
        on += w if ON[i] else z
        off += z if ON[i] else w
    books[0] += on
    books[1] += off
    books[2] += rf
    books[3] += ab


@njit(**BLOCK_JIT)
def _block_plane(m, z0, inv_a, reach2, OX, OY, OZ, DX, DY, DZ, W, X, Y, E, VX, VY):
    """:func:`plane_values` of a block's rays (a vector loop)."""
    for i in range(m):
        X[i], Y[i], E[i], VX[i], VY[i] = plane_values(z0, inv_a, reach2, OX[i], OY[i], OZ[i], DX[i], DY[i], DZ[i],
                                                      W[i])


@njit(**INLINE)
def pixel_index(ca, sa, ipx, ipy, cx, cy, wf, hf, W, C, off, x, y, e):
    """Where ``(x, y)`` turned by ``(ca, sa)`` lands in a pass's flat images (``cx, cy`` include the
    half pixel, ``wf, hf`` are ``W, H`` as floats), or -1 off the grid or for ``e = 0``."""
    zero = cx - cx
    cf = (ca * x - sa * y) * ipx + cx
    rf = (sa * x + ca * y) * ipy + cy
    inb = (cf >= zero) & (rf >= zero) & (cf < wf) & (rf < hf) & (e != zero)
    col = np.int64(cf if inb else zero)
    row = np.int64(rf if inb else zero)
    return (off + (row * W + col) * C) if inb else -1


@njit(**INLINE)
def plane_values(z0, inv_a, reach2, ox, oy, oz, dx, dy, dz, w):
    """Where a ray crosses the plane ``z0`` and what it adds there: ``(x, y, E, V_x, V_y)`` with
    ``E = w / A`` and ``V = w l / (A |l_z|)`` (``l = -d``, ``|l_z| = d_z > 0`` toward the gel);
    ``E = 0`` for a ray that does not reach it or cannot land on the grid under any rotation."""
    zero = z0 - z0
    t = (z0 - oz) / dz
    x = ox + t * dx
    y = oy + t * dy
    ok = (dz != zero) & (t > zero) & (x * x + y * y <= reach2)
    e = (w * inv_a) if ok else zero
    sv = -e / dz
    return (x if ok else zero), (y if ok else zero), e, sv * dx, sv * dy


@njit(**BLOCK_JIT)
def _block_scatter(m, ca, sa, ipx, ipy, cx, cy, H, W, C, off, X, Y, E, VX, VY, IDX, out):
    """Bin a block on one pass (rotated by ``(ca, sa)``): pixel indices in a vector loop, then the adds.

    (A branch-free variant adding the rays off the grid to one trash pixel ran 1.7x slower: those
    adds form one chain through memory.)"""
    wf = _fl(W, cx)
    hf = _fl(H, cx)
    for i in range(m):
        IDX[i] = pixel_index(ca, sa, ipx, ipy, cx, cy, wf, hf, W, C, off, X[i], Y[i], E[i])
    if C == 1:
        for i in range(m):
            j = IDX[i]
            if j >= 0:
                out[j] += E[i]
    else:
        for i in range(m):
            j = IDX[i]
            if j >= 0:
                out[j] += E[i]
                out[j + 1] += VX[i]
                out[j + 2] += VY[i]


@njit(**JIT)
def _block_bin(P, PT, PI, m, OX, OY, OZ, DX, DY, DZ, W, X, Y, E, VX, VY, IDX, out):
    """Bin a block's rays on every pass (a plane crossing per height, shared by its angles)."""
    one = P[P_ONE]
    zp = -one
    for p in range(PT.shape[0]):
        if p == 0 or PT[p, 0] != zp:
            zp = PT[p, 0]
            _block_plane(m, zp, PT[p, 7], PT[p, 8], OX, OY, OZ, DX, DY, DZ, W, X, Y, E, VX, VY)
        _block_scatter(m, PT[p, 1], PT[p, 2], PT[p, 3], PT[p, 4], PT[p, 5], PT[p, 6], PI[p, 0], PI[p, 1],
                       PI[p, 2], PI[p, 3], X, Y, E, VX, VY, IDX, out)


@njit(**JIT)
def _floats10(B, ft):
    """Ten block arrays of the kernel's float type."""
    return (np.empty(B, ft), np.empty(B, ft), np.empty(B, ft), np.empty(B, ft), np.empty(B, ft), np.empty(B, ft),
            np.empty(B, ft), np.empty(B, ft), np.empty(B, ft), np.empty(B, ft))


@njit(cache=True, nogil=True, **JIT)
def trace_range(P, F, seeds, tab, PT, PI, out, books, counts, lo, hi, redo):
    """Trace rays ``lo .. hi-1`` of one LED into one slot's images, books and counters.

    Parameters
    ----------
    P, F : tuples of the scene's parameters (:func:`sim.optics.engine.kernel_params`, :data:`P_SLOTS`, :data:`F_SLOTS`).
    seeds : uint64 (3,) sampler seeds.
    tab : (4, k) grid tables (:func:`sim.optics.engine.grid_tables`; any (4, 1) array for other samplers).
    PT : (Q, 9) per binning pass: plane ``z``, cos and sin of its angle, ``1/px``, ``1/py``,
        ``cx + 0.5``, ``cy + 0.5``, ``1/A`` and the grid's reach squared (kernel float type).
    PI : (Q, 4) int64 per pass: ``H``, ``W``, channels ``C`` (3 with V, else 1), offset in ``out``.
    out : (total,) the slot's images of every pass, (H * W, C) each, flat; added to.
    books : (4,) float64 (:data:`BOOKS`) and counts : (5,) int64 (:data:`COUNTS`), added to.
    redo : (R,) int64: receives the rays only :func:`trace_ray` can finish (neither booked nor binned
        here; :func:`trace_redo` does that).

    Returns ``(next, r)``: the first ray not traced (``hi`` unless ``redo`` filled up first) and the
    number of rays written to ``redo``. Releases the GIL: :func:`sim.optics.engine.trace_cpu` runs
    one slot per thread.
    """
    one = P[P_ONE]
    zero = one - one
    ft = tab.dtype
    B = BLOCK
    # The block's arrays: each its own allocation (BLOCK_JIT tells LLVM none overlaps another).
    EX, EY, EZ, T, SN, DSN, RHO, S, THI, E0 = _floats10(B, ft)
    PX, PY, PZ, IX, IY, IZ, WI, X1, X2, X12 = _floats10(B, ft)
    X0, OX, OY, OZ, DX, DY, DZ, W, RF, AB = _floats10(B, ft)
    X, Y, E, VX, VY, _, _, _, _, _ = _floats10(B, ft)
    ACT, DEAD, INS, BOX, UNC, HIT, STOP, SEL = (np.empty(B, np.bool_), np.empty(B, np.bool_), np.empty(B, np.bool_),
                                                np.empty(B, np.bool_), np.empty(B, np.bool_), np.empty(B, np.bool_),
                                                np.empty(B, np.bool_), np.empty(B, np.bool_))
    IDX = np.empty(B, np.int64)
    CODE = np.empty(B, np.int32)
    cnt = np.zeros(6, np.int64)
    lens = F[F_LENS] != 0
    r = 0
    start = lo
    while start < hi:
        m = min(B, hi - start)
        if r + m > redo.shape[0]:
            break
        _block_emit(P, F, seeds, tab, start, m, EX, EY, EZ)
        if lens:
            # in: the swept-arc side's entry solve, then refraction in and the start of the way out
            if _block_start(P, F, m, EX, EY, EZ, T, SN, DSN, RHO, S, ACT, DEAD, THI, INS, BOX):
                _solve(P, F, True, m, P[P_SRC_X], P[P_SRC_Y], P[P_SRC_Z], EX, EY, EZ, T, SN, DSN, RHO, S, ACT, DEAD)
            _block_entry(P, m, T, SN, DSN, S, DEAD, THI, INS, E0, UNC)
            if _block_inside(P, F, m, EX, EY, EZ, E0, BOX, HIT, STOP, PX, PY, PZ, IX, IY, IZ, WI, RF, X1, X2, X12,
                             X0, T, SN, DSN, RHO, S, SEL, ACT, DEAD):
                # out through the side: its exit solve (toward the last root)
                _solve(P, F, False, m, PX, PY, PZ, IX, IY, IZ, T, SN, DSN, RHO, S, ACT, DEAD)
            _block_exit(P, F, m, EX, EY, EZ, UNC, HIT, STOP, PX, PY, PZ, IX, IY, IZ, WI, RF, X1, X2, X12, X0,
                        T, SN, S, SEL, DEAD, OX, OY, OZ, DX, DY, DZ, W, AB, CODE)
            for i in range(m):
                if CODE[i] == REDO:
                    redo[r] = start + i
                    r += 1
                    CODE[i] = OUT
                    W[i] = RF[i] = AB[i] = zero  # booked and binned by trace_redo
        else:
            for i in range(m):
                OX[i], OY[i], OZ[i], DX[i], DY[i], DZ[i] = P[P_SRC_X], P[P_SRC_Y], P[P_SRC_Z], EX[i], EY[i], EZ[i]
                W[i], RF[i], AB[i], CODE[i] = P[P_W0], zero, zero, OUT
        _block_books(P, m, OX, OY, OZ, DX, DY, DZ, W, RF, AB, CODE, ACT, books, cnt)
        _block_bin(P, PT, PI, m, OX, OY, OZ, DX, DY, DZ, W, X, Y, E, VX, VY, IDX, out)
        start += m
    cnt[OUT] -= r  # the redo rays were counted as OUT above
    counts[0] += cnt[TIR_LOST]
    counts[2] += cnt[STOPPED]
    counts[3] += cnt[LOST]
    counts[4] += cnt[UNCONVERGED]
    return start, r


@njit(cache=True, nogil=True, **JIT)
def trace_redo(P, F, seeds, tab, PT, PI, out, books, counts, redo, r):
    """Rays ``redo[:r]`` through the scalar :func:`trace_ray`, booked and binned like :func:`trace_range`'s.

    A separate entry point, compiled the first time a scene needs it (TIR to follow, with the
    internal_bounces effect): the default scene's trace never does.
    """
    ft = tab.dtype
    m = r
    OX, OY, OZ = np.empty(m, ft), np.empty(m, ft), np.empty(m, ft)
    DX, DY, DZ = np.empty(m, ft), np.empty(m, ft), np.empty(m, ft)
    W, RF, AB = np.empty(m, ft), np.empty(m, ft), np.empty(m, ft)
    X, Y, E, VX, VY = np.empty(m, ft), np.empty(m, ft), np.empty(m, ft), np.empty(m, ft), np.empty(m, ft)
    CODE = np.empty(m, np.int32)
    IDX = np.empty(m, np.int64)
    cnt = np.zeros(6, np.int64)
    bounces = 0
    for i in range(m):
        dx, dy, dz = emit(P, F, seeds, tab, redo[i])
        OX[i], OY[i], OZ[i], DX[i], DY[i], DZ[i], W[i], RF[i], AB[i], CODE[i], nb = trace_ray(
            P, F, P[P_SRC_X], P[P_SRC_Y], P[P_SRC_Z], dx, dy, dz, P[P_W0])
        bounces += nb
    _block_books(P, m, OX, OY, OZ, DX, DY, DZ, W, RF, AB, CODE, np.empty(m, np.bool_), books, cnt)
    _block_bin(P, PT, PI, m, OX, OY, OZ, DX, DY, DZ, W, X, Y, E, VX, VY, IDX, out)
    counts[0] += cnt[TIR_LOST]
    counts[1] += bounces
    counts[2] += cnt[STOPPED]
    counts[3] += cnt[LOST]
    counts[4] += cnt[UNCONVERGED]


@njit(cache=True, **JIT)
def trace_rays(P, F, O, D, W, out):
    """Given rays (origins ``O`` (N, 3), unit directions ``D`` (N, 3), powers ``W`` (N,)) through the lens
    with :func:`trace_ray`: ``out`` (N, 11) gets the ray leaving the optics (origin, direction,
    power), the power reflected and absorbed, the fate code and the TIR bounces."""
    for i in range(O.shape[0]):
        r = trace_ray(P, F, O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2], W[i])
        out[i, 0], out[i, 1], out[i, 2], out[i, 3], out[i, 4], out[i, 5] = r[0], r[1], r[2], r[3], r[4], r[5]
        out[i, 6], out[i, 7], out[i, 8], out[i, 9], out[i, 10] = r[6], r[7], r[8], r[9], r[10]
