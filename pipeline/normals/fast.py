"""The live near-field path: normal-equation factors precomputed once, a frame is one fused pass.

Why: the per-pixel light matrices ``L(x) (N, 3)`` of a calibration (or an illumination model)
never change between frames, so everything that depends only on them (the per-group Gram
matrices ``Q_g(x) = sum_{k in g} L_k L_k^T``, the inverse of ``sum_g Q_g``, the condition
number and the validity it implies) is computed once, in float64, by :class:`NearFieldFast`.
A frame then costs one pass that reads each observation once: per pixel the moments
``r_g = sum_k I_k L_k`` and ``S_g = sum_k I_k^2`` (3N + N multiply-adds), ``b = A^-1 sum_g r_g``,
the per-group albedo ``rho_g = n.r_g / n^T Q_g n`` and the residual from the same moments.
This is exactly the eager :class:`pipeline.normals.nearfield.NearFieldSolver` (the same
normal equations, the same per-group albedo alternation when the channels see different
lights, the same masks), which stays as the reference: ``tests/pipeline/normals/test_fast_paths.py``
pins the two together to float32 rounding.

The kernel is Numba, compiled once and cached on disk (``cache=True``; ``NUMBA_CACHE_DIR``
moves the cache): a first use in a fresh process loads it in well under a second. It works
on blocks of pixels with pixel-contiguous planes (observations de-interleaved once per frame
by OpenCV's SIMD channel split, the light field stored ``(N, 3, M)``), so the inner loops run
over pixels and vectorise.

Integer frames only (uint8/uint16: no NaN can reach the moments); float frames with NaN/Inf
go to the eager solver. Lights that are not finite at a pixel make that pixel invalid here
(the eager solver would down-weight the observation instead).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from pipeline.normals.result import COND_CAP, NormalResult

__all__ = ["NearFieldFast", "frame_planes_np", "split_into", "run_split", "BLOCK"]

#: Pixels per block: the block's accumulators (4 G planes) and light rows stay in L1/L2.
BLOCK = 512


_POOL = None


def run_split(fn, M: int, threads: int = 1) -> None:
    """``fn(start, stop)`` over ``[0, M)`` in ``threads`` contiguous parts, in parallel (``fn``
    must release the GIL: a ``nogil`` Numba kernel). Parts are multiples of :data:`BLOCK`."""
    threads = max(1, int(threads))
    if threads == 1 or M <= BLOCK:
        fn(0, M)
        return
    global _POOL
    from concurrent.futures import ThreadPoolExecutor

    if _POOL is None or _POOL._max_workers < threads:
        _POOL = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="iristac-fast")
    step = -(-M // threads)
    step = -(-step // BLOCK) * BLOCK
    futures = [_POOL.submit(fn, a, min(M, a + step)) for a in range(0, M, step)]
    for f in futures:
        f.result()


def frame_planes_np(frames: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
    """Frames ``(P, H, W, C)`` as contiguous observation planes ``(P * C, H * W)`` (pattern-major,
    channel-minor), same dtype; ``index`` keeps only those pixels (``(M,)`` flat indices).

    Examples
    --------
    >>> f = np.arange(2 * 1 * 2 * 3, dtype=np.uint8).reshape(2, 1, 2, 3)
    >>> frame_planes_np(f).tolist()
    [[0, 3], [1, 4], [2, 5], [6, 9], [7, 10], [8, 11]]
    """
    a = np.asarray(frames)
    P, H, W, C = a.shape
    planes = np.empty((P * C, H * W), a.dtype)
    split_into(a, planes, 0, H * W)
    return planes if index is None else np.ascontiguousarray(planes[:, index])


def split_into(frames: np.ndarray, planes: np.ndarray, start: int, stop: int) -> None:
    """Pixels ``start:stop`` of frames ``(P, H, W, C)`` into ``planes[:, start:stop]`` (``planes``
    ``(P * C, H * W)``, same dtype), in place (splitting into new arrays and copying them took
    ~2.5x as long: 0.26 against 0.10 ms for 8 RGB frames at 320 x 240)."""
    P, H, W, C = frames.shape
    n = stop - start
    if frames.dtype in (np.uint8, np.uint16, np.float32) and 1 < C <= 4 and frames.flags.c_contiguous:
        import cv2  # SIMD de-interleave (~3x numpy's transposing copy), written into the planes

        for p in range(P):
            src = frames[p].reshape(H * W, 1, C)[start:stop]
            dst = [planes[p * C + c, start:stop].reshape(n, 1) for c in range(C)]
            out = cv2.split(src, dst)
            for d, o in zip(dst, out):
                if o.ctypes.data != d.ctypes.data:  # OpenCV reallocated instead of writing in place
                    d[...] = o.reshape(d.shape)
    else:
        planes[:, start:stop] = frames.reshape(P, H * W, C)[:, start:stop].transpose(0, 2, 1).reshape(P * C, n)


_TINY = np.float32(1.1754944e-38)
# Every kernel is compiled with error_model="numpy": Numba's default (Python semantics) checks
# each division for a zero divisor to raise ZeroDivisionError, and that branch keeps the loops
# from vectorising (measured: SiLU on a block, 439 -> 14 ns per pixel). The kernels guard their
# divisors themselves.


@njit(cache=True, nogil=True, error_model="numpy")
def _quad(Q, g, x, n0, n1, n2):  # pragma: no cover - compiled
    """``n^T Q_g n`` with ``Q (G, 6, M)`` holding (xx, xy, xz, yy, yz, zz)."""
    return (Q[g, 0, x] * n0 * n0 + Q[g, 3, x] * n1 * n1 + Q[g, 5, x] * n2 * n2
            + np.float32(2.0) * (Q[g, 1, x] * n0 * n1 + Q[g, 2, x] * n0 * n2 + Q[g, 4, x] * n1 * n2))


def blocked(a: np.ndarray) -> np.ndarray:
    """``(..., M)`` -> ``(ceil(M / BLOCK), ..., BLOCK)`` float32, zero-padded: each block's data is
    one contiguous run, read as one stream (the per-plane layout made ~100 streams per block,
    more than the prefetchers follow: 3x slower once the field no longer fits the cache)."""
    M = a.shape[-1]
    nb = -(-M // BLOCK)
    pad = np.zeros(a.shape[:-1] + (nb * BLOCK,), np.float32)
    pad[..., :M] = a
    return np.ascontiguousarray(np.moveaxis(pad.reshape(a.shape[:-1] + (nb, BLOCK)), -2, 0))


@njit(cache=True, nogil=True, error_model="numpy")
def _nearfield_kernel(obs, dark, invflat, L, inv, Q, scale, groups, num_groups, valid0, iterations, start, stop,  # noqa: C901 - compiled: the loop body stays one function so Numba vectorises it
                      normals, albedo, residual, mask):  # pragma: no cover - compiled
    """Pixels ``start:stop`` of observation planes ``obs (N, M)``: moments, solve, outputs.

    Blocked layout (:func:`blocked`, block ``b`` = pixels ``512 b ...``): ``L (nb, N, 3, 512)``,
    ``inv (nb, 6, 512)`` (symmetric: xx, xy, xz, yy, yz, zz), ``Q (nb, G, 6, 512)``, ``dark``/``invflat`` ``(nb, N, 512)`` or
    ``(0, 0, 0)`` when absent, float32; ``valid0 (M,)`` bool; ``start`` a multiple of 512.
    Channels sharing their lights (``scale (nb, G, 512)``, else ``(0, 0, 0)``): observation
    ``k`` (pattern ``k // G``, channel ``g = k % G``) has the light ``scale_g L[k // G]``, so
    ``L`` is ``(nb, P, 3, 512)`` and ``Q`` ``(nb, 1, 6, 512)`` (of the unscaled lights): a third
    of the memory a frame reads.
    Per block the moments are accumulated over pixel-contiguous slices (separate arrays: no
    aliasing, so the loops vectorise), then every pixel is finished from them.
    """
    N = obs.shape[0]
    G = num_groups
    has_dark = dark.shape[0] > 0
    has_flat = invflat.shape[0] > 0
    r0 = np.empty((G, 512), np.float32)
    r1 = np.empty((G, 512), np.float32)
    r2 = np.empty((G, 512), np.float32)
    S = np.empty((G, 512), np.float32)
    Ib = np.empty(512, np.float32)
    t0 = np.empty(512, np.float32)
    t1 = np.empty(512, np.float32)
    t2 = np.empty(512, np.float32)
    bb0 = np.empty(512, np.float32)
    bb1 = np.empty(512, np.float32)
    bb2 = np.empty(512, np.float32)
    n0b = np.empty(512, np.float32)
    n1b = np.empty(512, np.float32)
    n2b = np.empty(512, np.float32)
    mn = np.empty(512, np.float32)
    okb = np.empty(512, np.bool_)
    rh = np.empty((G, 512), np.float32)
    a00 = np.empty(512, np.float32)
    a01 = np.empty(512, np.float32)
    a02 = np.empty(512, np.float32)
    a11 = np.empty(512, np.float32)
    a12 = np.empty(512, np.float32)
    a22 = np.empty(512, np.float32)
    shared = scale.shape[0] > 0
    Qs = np.empty((G, 6, 512), np.float32)
    for j0 in range(start, stop, 512):
        j1 = min(stop, j0 + 512)
        B = j1 - j0
        blk = j0 // 512
        Lb = L[blk]
        Qb = Q[blk]
        ib = inv[blk]
        r0[:, :B] = 0.0
        r1[:, :B] = 0.0
        r2[:, :B] = 0.0
        S[:, :B] = 0.0
        for k in range(N):
            g = groups[k]
            o = obs[k, j0:j1]
            if has_dark or has_flat:
                for j in range(B):
                    v = np.float32(o[j])
                    if has_dark:
                        v = v - dark[blk, k, j]
                    if has_flat:
                        v = v * invflat[blk, k, j]
                    Ib[j] = v
            else:
                for j in range(B):
                    Ib[j] = np.float32(o[j])
            lk = k // G if shared else k
            l0 = Lb[lk, 0, :B]
            l1 = Lb[lk, 1, :B]
            l2 = Lb[lk, 2, :B]
            a0 = r0[g, :B]
            a1 = r1[g, :B]
            a2 = r2[g, :B]
            s = S[g, :B]
            for j in range(B):
                v = Ib[j]
                a0[j] += v * l0[j]
                a1[j] += v * l1[j]
                a2[j] += v * l2[j]
                s[j] += v * v
        if shared:
            sb = scale[blk]
            for g in range(G):
                for j in range(B):
                    f = sb[g, j]
                    r0[g, j] *= f
                    r1[g, j] *= f
                    r2[g, j] *= f
                    for t in range(6):
                        Qs[g, t, j] = f * f * Qb[0, t, j]
            Qb = Qs
        # Finish every pixel of the block from its moments, as loops over pixels (they
        # vectorise; the group loops are outside them).
        for j in range(B):
            t0[j] = r0[0, j]
            t1[j] = r1[0, j]
            t2[j] = r2[0, j]
        for g in range(1, G):
            for j in range(B):
                t0[j] += r0[g, j]
                t1[j] += r1[g, j]
                t2[j] += r2[g, j]
        for j in range(B):
            bb0[j] = ib[0, j] * t0[j] + ib[1, j] * t1[j] + ib[2, j] * t2[j]
            bb1[j] = ib[1, j] * t0[j] + ib[3, j] * t1[j] + ib[4, j] * t2[j]
            bb2[j] = ib[2, j] * t0[j] + ib[4, j] * t1[j] + ib[5, j] * t2[j]
        if G > 1:
            for _ in range(iterations):
                # Per-group albedo alternation (pipeline.normals._lstsq.solve): rescale the
                # model by each group's relative albedo and solve again.
                for j in range(B):
                    nrm = np.sqrt(bb0[j] * bb0[j] + bb1[j] * bb1[j] + bb2[j] * bb2[j])
                    sc = np.float32(1.0) / max(nrm, _TINY)
                    n0b[j] = bb0[j] * sc
                    n1b[j] = bb1[j] * sc
                    n2b[j] = bb2[j] * sc
                    mn[j] = 0.0
                for g in range(G):
                    for j in range(B):
                        p = n0b[j] * r0[g, j] + n1b[j] * r1[g, j] + n2b[j] * r2[g, j]
                        rr = p / max(_quad(Qb, g, j, n0b[j], n1b[j], n2b[j]), _TINY)
                        rh[g, j] = rr
                        mn[j] += rr
                for j in range(B):
                    mn[j] = mn[j] / np.float32(G)
                    a00[j] = 0.0
                    a01[j] = 0.0
                    a02[j] = 0.0
                    a11[j] = 0.0
                    a12[j] = 0.0
                    a22[j] = 0.0
                    t0[j] = 0.0
                    t1[j] = 0.0
                    t2[j] = 0.0
                for g in range(G):
                    for j in range(B):
                        rel = rh[g, j] / mn[j] if (rh[g, j] > 0 and mn[j] > 0) else np.float32(1.0)
                        w = rel * rel
                        a00[j] += w * Qb[g, 0, j]
                        a01[j] += w * Qb[g, 1, j]
                        a02[j] += w * Qb[g, 2, j]
                        a11[j] += w * Qb[g, 3, j]
                        a12[j] += w * Qb[g, 4, j]
                        a22[j] += w * Qb[g, 5, j]
                        t0[j] += rel * r0[g, j]
                        t1[j] += rel * r1[g, j]
                        t2[j] += rel * r2[g, j]
                for j in range(B):
                    c00 = a11[j] * a22[j] - a12[j] * a12[j]
                    c01 = a12[j] * a02[j] - a01[j] * a22[j]
                    c02 = a01[j] * a12[j] - a11[j] * a02[j]
                    c11 = a00[j] * a22[j] - a02[j] * a02[j]
                    c12 = a02[j] * a01[j] - a00[j] * a12[j]
                    c22 = a00[j] * a11[j] - a01[j] * a01[j]
                    det = a00[j] * c00 + a01[j] * c01 + a02[j] * c02
                    idet = np.float32(1.0) / det if det != 0 else np.float32(0.0)
                    bb0[j] = (c00 * t0[j] + c01 * t1[j] + c02 * t2[j]) * idet
                    bb1[j] = (c01 * t0[j] + c11 * t1[j] + c12 * t2[j]) * idet
                    bb2[j] = (c02 * t0[j] + c12 * t1[j] + c22 * t2[j]) * idet
        for j in range(B):
            x = j0 + j
            nrm = np.sqrt(bb0[j] * bb0[j] + bb1[j] * bb1[j] + bb2[j] * bb2[j])
            sc = np.float32(1.0) / max(nrm, _TINY)
            n2 = bb2[j] * sc
            ok = valid0[x] and nrm > 0 and n2 > 0
            okb[j] = ok
            n0b[j] = bb0[j] * sc if ok else np.float32(0.0)
            n1b[j] = bb1[j] * sc if ok else np.float32(0.0)
            n2b[j] = n2 if ok else np.float32(1.0)
            mn[j] = 0.0  # explained
            t0[j] = 0.0  # total
        for g in range(G):
            for j in range(B):
                p = n0b[j] * r0[g, j] + n1b[j] * r1[g, j] + n2b[j] * r2[g, j]
                q = max(_quad(Qb, g, j, n0b[j], n1b[j], n2b[j]), _TINY)
                rh[g, j] = p / q if okb[j] else np.float32(0.0)
                mn[j] += p * p / q
                t0[j] += S[g, j]
        for j in range(B):
            x = j0 + j
            ok = okb[j]
            residual[x] = np.sqrt(max(t0[j] - mn[j], np.float32(0.0)) / np.float32(N)) if ok else np.float32(0.0)
            normals[x, 0] = n0b[j]
            normals[x, 1] = n1b[j]
            normals[x, 2] = n2b[j]
            for g in range(G):
                albedo[x, g] = rh[g, j]
            mask[x] = ok


class NearFieldFast:
    """Near-field photometric stereo with everything that depends on the lights precomputed.

    Parameters
    ----------
    lights : ndarray, shape (N, H, W, 3)
        Per-pixel light vectors of the ``N = P * C`` observations (pattern-major,
        channel-minor), e.g. a calibration's ``light_field (P, C, H, W, 3)`` reshaped.
    groups : ndarray, shape (N,), optional
        Albedo group (camera channel) of each observation; default: one group.
    flat_field : ndarray, shape (N, H, W), optional
        Observations are divided by it first (where positive; elsewhere the pixel is invalid).
    max_condition : float
        Pixels with a worse-conditioned light matrix are masked.
    albedo_iterations : int, optional
        Per-group albedo alternation steps; None: as :class:`NearFieldSolver` decides (3 when
        the channels see different lights, else 0).
    mask : ndarray, shape (H, W), bool, optional
        Solve only these pixels (the rest come back invalid).
    dark : ndarray, shape (H, W, C), optional
        Dark frame subtracted from every pattern.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> L = rng.normal(size=(6, 2, 3, 3)); L[..., 2] = np.abs(L[..., 2]) + 2
    >>> n = np.array([0.0, 0.6, 0.8])
    >>> I = np.clip(np.einsum("nhwk,k->nhw", L, n) * 40, 0, 255).round().astype(np.uint8)
    >>> fast = NearFieldFast(L)
    >>> res = fast.solve(I.reshape(6, 2, 3, 1))   # (P, H, W, C) frames, here C = 1
    >>> bool(res.mask.all()), float(np.abs(res.normals - n).max()) < 0.02
    (True, True)
    """

    def __init__(self, lights, *, groups=None, flat_field=None, max_condition: float = 1e3,
                 albedo_iterations: int | None = None, mask=None, dark=None):
        L = np.asarray(lights, np.float64)
        if L.ndim != 4 or L.shape[-1] != 3:
            raise ValueError(f"NearFieldFast: lights must have shape (N_obs, H, W, 3), got {L.shape}")
        N, H, W, _ = L.shape
        self.n_obs, self.shape = N, (H, W)
        self.groups = np.zeros(N, np.int64) if groups is None else np.asarray(groups, np.int64)
        if self.groups.shape != (N,) or self.groups.min() < 0:
            raise ValueError(f"NearFieldFast: groups must be ({N},) non-negative integers, got {self.groups.shape}")
        self.num_groups = int(self.groups.max()) + 1
        self.max_condition = float(max_condition)
        full = np.ones((H, W), bool) if mask is None else np.asarray(mask, bool)
        if full.shape != (H, W):
            raise ValueError(f"NearFieldFast: mask must have shape {(H, W)}, got {full.shape}")
        self.region = None if mask is None else full
        self.index = np.flatnonzero(full.ravel()).astype(np.int64)
        Lm = L.reshape(N, H * W, 3)[:, self.index]  # (N, M, 3)
        finite = np.isfinite(Lm).all(axis=(0, 2))
        Lm = np.where(np.isfinite(Lm), Lm, 0.0)
        # Per-group Gram matrices (float64), their sum's inverse and condition number.
        Qg = np.stack([np.einsum("kmi,kmj->mij", Lm[self.groups == g], Lm[self.groups == g])
                       for g in range(self.num_groups)])  # (G, M, 3, 3)
        A = Qg.sum(0)
        det = np.linalg.det(A)
        invertible = np.isfinite(det) & (det != 0)
        inv = np.zeros_like(A)
        inv[invertible] = np.linalg.inv(A[invertible])
        ev = np.linalg.eigvalsh(A)  # ascending
        with np.errstate(divide="ignore", invalid="ignore"):
            cond = np.sqrt(np.clip(ev[:, 2] / np.where(ev[:, 0] > 0, ev[:, 0], 1.0), 1.0, None))
        bad = (ev[:, 0] <= 0) | (ev[:, 2] <= 0) | ~np.isfinite(cond)
        self.condition_m = np.where(bad, COND_CAP, np.minimum(cond, COND_CAP)).astype(np.float32)
        sym = [0, 1, 2, 4, 5, 8]  # xx, xy, xz, yy, yz, zz of a symmetric 3x3
        self.inv = blocked(inv.reshape(-1, 9)[:, sym].T)  # (nb, 6, 512): the inverse is symmetric too
        scale = self._shared_scale(Lm)
        counts = np.bincount(self.groups, minlength=self.num_groups)
        if albedo_iterations is None:
            shared = self._channels_share_lights(Lm)
            albedo_iterations = 0 if shared or (counts < 3).any() else 3
        self.iterations = int(albedo_iterations) if self.num_groups > 1 else 0
        # White patterns (channels share their lights, no alternation): the pseudo-inverse
        # kernel (pipeline.normals.fast_shared), which reads fewer bytes and vectorises.
        self.pinv = scale is not None and self.iterations == 0
        if self.pinv:
            from pipeline.normals.fast_shared import shared_factors

            L0 = Lm[::self.num_groups]  # (P, M, 3): the first channel's lights
            Q0 = np.einsum("kmi,kmj->mij", L0, L0)
            Pi = shared_factors(L0, Q0, invertible)
            self.Lt = blocked(Pi.transpose(0, 2, 1))  # (nb, P, 3, 512): Q_0^-1 L_p
            self.Q = blocked(Q0.reshape(-1, 9)[:, sym].T)  # (nb, 6, 512)
            self.inv = np.zeros((0, 0, 0), np.float32)  # folded into Pi; scale: below, with the validity
        elif scale is None:
            self.Lt = blocked(Lm.transpose(0, 2, 1))  # (nb, N, 3, 512)
            self.Q = blocked(Qg.reshape(self.num_groups, -1, 9)[:, :, sym].transpose(0, 2, 1))  # (nb, G, 6, 512)
            self.scale = np.zeros((0, 0, 0), np.float32)
        else:
            L0 = Lm[::self.num_groups]  # (P, M, 3): the first channel's lights
            Q0 = np.einsum("kmi,kmj->mij", L0, L0).reshape(-1, 9)[:, sym]
            self.Lt = blocked(L0.transpose(0, 2, 1))  # (nb, P, 3, 512)
            self.Q = blocked(Q0.T[None])  # (nb, 1, 6, 512)
            self.scale = blocked(scale)  # (nb, G, 512)
        self.shared = scale is not None
        self.valid0 = finite & invertible & (self.condition_m <= self.max_condition) & (N >= 3)
        M = len(self.index)
        if flat_field is not None:
            f = np.asarray(flat_field, np.float64).reshape(N, H * W)[:, self.index]
            self.valid0 &= (f > 0).all(axis=0)
            self.invflat = blocked(np.where(f > 0, 1.0 / np.where(f > 0, f, 1.0), 0.0))
        else:
            self.invflat = np.zeros((0, 0, 0), np.float32)  # absent: the kernel skips it
        if self.pinv:  # the validity folded into the scalars: the kernel reads no mask
            self.scale = blocked(np.where(self.valid0, scale, 0.0))
        self._count = np.full(M, N, np.int32)  # every observation is used: the same every frame
        self._count.flags.writeable = False  # shared by every result (as the condition map)
        self.set_dark(dark)

    def _shared_scale(self, Lm: np.ndarray, rtol: float = 2e-7):
        """``scale (G, M)`` when every channel's lights are, at every pixel, one scalar times the
        first channel's to float32 rounding (white patterns: the channels see the same LEDs),
        observations being pattern-major and channel-minor; else None."""
        G, N = self.num_groups, self.n_obs
        if G < 2 or N % G or not np.array_equal(self.groups, np.tile(np.arange(G), N // G)):
            return None
        L = Lm.reshape(N // G, G, -1, 3)  # (P, G, M, 3)
        ref = L[:, 0]
        den = np.einsum("pmi,pmi->m", ref, ref)
        scale = np.ones((G, Lm.shape[1]))
        for g in range(1, G):
            a = np.einsum("pmi,pmi->m", L[:, g], ref) / np.where(den > 0, den, 1.0)
            err = np.abs(L[:, g] - a[None, :, None] * ref).max(axis=(0, 2))
            if (err > rtol * np.abs(L[:, g]).max(axis=(0, 2)) + 1e-30).any():
                return None
            scale[g] = a
        return scale

    def _channels_share_lights(self, Lm: np.ndarray, rtol: float = 1e-4) -> bool:
        """As :func:`pipeline.normals._lstsq.channels_share_lights`: every group's lights a scalar
        multiple of the first group's (then a joint solve is exact)."""
        sel = [np.flatnonzero(self.groups == g) for g in range(self.num_groups)]
        ref = Lm[sel[0]]
        ref_norm = float((ref * ref).sum())
        for s in sel[1:]:
            Lg = Lm[s]
            if Lg.shape != ref.shape:
                return False
            a = float((Lg * ref).sum()) / max(ref_norm, 1e-300)
            if float(((Lg - a * ref) ** 2).sum()) > rtol ** 2 * max(float((Lg * Lg).sum()), 1e-300):
                return False
        return True

    def set_dark(self, dark) -> None:
        """Subtract ``dark (H, W, C)`` (None: nothing) from every later frame."""
        N = self.n_obs
        if dark is None:
            self.dark = np.zeros((0, 0, 0), np.float32)  # absent: the kernel skips it
            return
        d = np.asarray(dark, np.float32)
        H, W = self.shape
        C = d.shape[-1]
        if d.shape != (H, W, C) or N % C:
            raise ValueError(f"NearFieldFast: dark must be (H, W, C) = ({H}, {W}, C) with C dividing {N}, got {d.shape}")
        planes = frame_planes_np(np.broadcast_to(d, (N // C, H, W, C)).copy(), self.index)
        self.dark = blocked(planes.astype(np.float32))

    @property
    def pixels(self) -> int:
        return int(len(self.index))

    def solve_planes(self, planes: np.ndarray, threads: int = 1):
        """The raw kernel on observation planes ``(N, M)`` (integer dtype) of the solved pixels:
        ``(normals (M, 3), albedo (M, G), residual (M,), mask (M,))`` float32/bool.

        ``threads`` > 1 splits the pixels between that many threads (the kernel releases the
        GIL); a frame this small is memory-bound, so two threads gain what the second core's
        share of the memory bandwidth gives.
        """
        M = len(self.index)
        if planes.shape != (self.n_obs, M):
            raise ValueError(f"NearFieldFast: observation planes must be ({self.n_obs}, {M}), got {planes.shape}")
        residual = np.empty(M, np.float32)
        mask = np.empty(M, np.bool_)
        if self.pinv:
            from pipeline.normals.fast_shared import shared_kernel

            args = (planes, self.dark, self.invflat, self.Lt, self.Q, self.scale)
            np_, ap = np.empty((3, M), np.float32), np.empty((self.num_groups, M), np.float32)
            run_split(lambda a, b: shared_kernel(*args, a, b, np_, ap, residual, mask), M, threads)
            # (M, 3) and (M, G) views of the planes, not copies: FastDST reads the planes back
            # without a split, and interleaving both cost two more passes over the frame.
            normals, albedo = np_.T, ap.T
        else:
            normals = np.empty((M, 3), np.float32)
            albedo = np.empty((M, self.num_groups), np.float32)
            outs = (normals, albedo, residual, mask)
            args = (planes, self.dark, self.invflat, self.Lt, self.inv, self.Q, self.scale, self.groups,
                    self.num_groups, self.valid0, self.iterations)
            run_split(lambda a, b: _nearfield_kernel(*args, a, b, *outs), M, threads)
        return normals, albedo, residual, mask

    def solve(self, frames, threads: int = 1) -> NormalResult:
        """Normals of one frame set ``(P, H, W, C)`` (uint8 or uint16; ``P * C = N``) on
        ``threads`` threads."""
        f = np.asarray(frames)
        if f.ndim != 4 or f.shape[1:3] != self.shape or f.shape[0] * f.shape[3] != self.n_obs:
            raise ValueError(f"NearFieldFast.solve: frames must be (P, {self.shape[0]}, {self.shape[1]}, C) with "
                             f"P * C = {self.n_obs}, got {f.shape}")
        if f.dtype.kind not in "ui":
            raise ValueError(f"NearFieldFast.solve: integer frames expected (uint8/uint16), got {f.dtype}; float "
                             f"frames go to the eager NearFieldSolver")
        planes = frame_planes_np(f, None if self.region is None else self.index)
        n, rho, res, ok = self.solve_planes(planes, threads)
        return self._result(n, rho, res, ok)

    def _result(self, n, rho, res, ok) -> NormalResult:
        H, W = self.shape
        if self.region is None:
            full = lambda a, fill: a.reshape((H, W) + a.shape[1:])  # noqa: E731
        else:
            def full(a, fill):
                out = np.empty((H * W,) + a.shape[1:], a.dtype)
                out[...] = fill
                out[self.index] = a
                return out.reshape((H, W) + a.shape[1:])
        cond = self.condition_m
        count = self._count
        return NormalResult(normals=full(n, np.array([0, 0, 1], np.float32)), albedo=full(rho, 0), residual=full(res, 0),
                            condition=full(cond, COND_CAP), mask=full(ok, False), count=full(count, 0),
                            meta={"solver": "nearfield", "method": "fast", "max_condition": self.max_condition})
