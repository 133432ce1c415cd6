"""The compiled near-field kernels of :class:`pipeline.normals.fast.NearFieldFast`.

Two estimators, each written once as the work on one block of 512 pixels (``_nearfield_block``,
``_shared_block``, inlined by Numba: ``inline="always"``), each driven by one kernel over
camera frames as they arrive, interleaved ``(K, P, H*W*C)``: pixels ``start:stop`` of every
frame, one block of every frame after the other (:func:`nearfield_batch`,
:func:`shared_batch`). A block's precomputed factors (about 60 KB) are read from memory once a
call and stay in the core's cache for the other frames; each frame's pixels of the block are
de-interleaved into observation planes in the kernel (:func:`gather_block`); the outputs are
written as whole-frame planes (:func:`_store_block`, which also scatters a region's pixels).
One frame (the live path, ``K = 1``) is split between threads by pixels; many frames
(``iristac bench live``'s frames rows, ``batch``/``reconstruct --threads``) by runs of pixels of
every frame, one call per run, so Python and its lock are entered a few times per thread and
batch, not once a frame.

The general kernel (:func:`nearfield_batch`) takes per-observation lights, per-channel Gram
matrices and the per-channel albedo alternation: the estimator of
:class:`pipeline.normals.nearfield.NearFieldSolver`. The second (:func:`shared_batch`) is its closed
form when every camera channel sees the same LEDs (white patterns): then the light
of observation ``(p, g)`` at a pixel is ``s_g(x) L_p(x)`` (:meth:`NearFieldFast._shared_scale`),
the Gram matrices are ``Q_g = s_g^2 Q_0`` with ``Q_0 = sum_p L_p L_p^T``, and the albedo
alternation is not needed (the joint solve is exact). Then the normal equations fold into
precomputed per-pixel rows: with ``Pi_p = Q_0^-1 L_p`` (float64, stored float32) and the
per-channel moments ``u_g = sum_p I_pg Pi_p``, ``S_g = sum_p I_pg^2``,

- ``b = sum_g s_g u_g / sum_g s_g^2`` (the least-squares solution ``A^-1 sum_g r_g``),
- ``n.r_g = s_g (Q_0 n).u_g`` and ``n^T Q_g n = s_g^2 n^T Q_0 n``, so the per-channel albedo
  ``rho_g = (Q_0 n).u_g / (s_g n^T Q_0 n)`` and the explained energy
  ``((Q_0 n).u_g)^2 / n^T Q_0 n`` come from the same moments.

Per pixel the frame reads ``Pi`` (3P floats), ``Q_0`` (6) and ``s`` (G): no separate inverse
and Gram planes, and every loop is a plain loop over a block's pixels with the per-channel
and per-pattern loops outside it (so it vectorises: the general kernel's finishing loops ran
at about 15 ns a pixel, these at a few). It is the same estimator as
:class:`pipeline.normals.nearfield.NearFieldSolver` (``tests/pipeline/normals/test_fast_paths.py``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["shared_factors", "gather_block", "nearfield_batch", "shared_batch"]

_TINY = np.float32(1.1754944e-38)
# Every kernel is compiled with error_model="numpy": Numba's default (Python semantics) checks
# each division for a zero divisor to raise ZeroDivisionError, and that branch keeps the loops
# from vectorising (measured: SiLU on a block, 439 -> 14 ns per pixel). The kernels guard their
# divisors themselves. Every function a cached kernel calls lives in this file: Numba's disk
# cache is keyed on the kernel's own source file, so a callee elsewhere could go stale.


def shared_factors(L0: np.ndarray, Q0: np.ndarray, invertible: np.ndarray):
    """``Pi (P, M, 3)`` float64: ``Q_0^-1 L_p`` per pixel (0 where ``Q_0`` is singular), from the
    first channel's lights ``L0 (P, M, 3)`` and their Gram matrices ``Q0 (M, 3, 3)``."""
    inv = np.zeros_like(Q0)
    inv[invertible] = np.linalg.inv(Q0[invertible])
    return np.einsum("mij,pmj->pmi", inv, L0)


@njit(nogil=True, error_model="numpy")
def gather_block(frame, index, j0, B, C, buf):  # pragma: no cover - compiled
    """Pixels ``j0:j0 + B`` (``index[j0:j0 + B]`` when ``index`` is not empty) of one interleaved
    frame ``(P, H*W*C)`` as observation planes into ``buf (P*C, 512)`` (pattern-major,
    channel-minor), zero beyond ``B``. Three channels and a whole block: a fixed stride and trip
    count, so LLVM vectorises the de-interleave (0.12 ms a frame of 8 RGB patterns at 320 x 240,
    as OpenCV's split; a run-time stride took 0.7 ms)."""
    P = frame.shape[0]
    if index.shape[0] == 0 and B == 512 and C == 3:
        for p in range(P):
            src = frame[p, 3 * j0:3 * j0 + 1536]
            for c in range(3):
                d = buf[3 * p + c]
                for j in range(512):
                    d[j] = src[3 * j + c]
        return
    for p in range(P):
        src = frame[p]
        for c in range(C):
            d = buf[p * C + c]
            for j in range(B):
                x = j0 + j if index.shape[0] == 0 else index[j0 + j]
                d[j] = src[C * x + c]
            for j in range(B, 512):
                d[j] = 0


@njit(cache=True, nogil=True, error_model="numpy")
def _quad(Q, g, x, n0, n1, n2):  # pragma: no cover - compiled
    """``n^T Q_g n`` with ``Q (G, 6, M)`` holding (xx, xy, xz, yy, yz, zz)."""
    return (Q[g, 0, x] * n0 * n0 + Q[g, 3, x] * n1 * n1 + Q[g, 5, x] * n2 * n2
            + np.float32(2.0) * (Q[g, 1, x] * n0 * n1 + Q[g, 2, x] * n0 * n2 + Q[g, 4, x] * n1 * n2))


@njit(inline="always", error_model="numpy")
def _nearfield_scratch(G):  # pragma: no cover - compiled
    """The general block's per-pixel scratch: one array each (separate arrays, so LLVM sees no
    aliasing between them and the loops vectorise)."""
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
    Qs = np.empty((G, 6, 512), np.float32)
    return (r0, r1, r2, S, Ib, t0, t1, t2, bb0, bb1, bb2, n0b, n1b, n2b, mn, okb, rh, a00, a01, a02, a11, a12, a22, Qs)


@njit(inline="always", error_model="numpy")
def _nearfield_block(obs, o0, B, j0, x0, dark, invflat, L, inv, Q, scale, groups, num_groups, valid0,  # noqa: C901 - compiled: the loop body stays one function so Numba vectorises it
                     iterations, scratch, normals, albedo, residual, mask):  # pragma: no cover - compiled
    """The block of pixels ``j0:j0 + B`` (``j0`` a multiple of 512): observations ``obs[:, o0:o0 + B]``,
    outputs at ``x0:x0 + B``. Blocked layout (:func:`pipeline.normals.fast.blocked`, block ``b`` =
    pixels ``512 b ...``): ``L (nb, N, 3, 512)``, ``inv (nb, 6, 512)`` (symmetric: xx, xy, xz, yy,
    yz, zz), ``Q (nb, G, 6, 512)``, ``dark``/``invflat`` ``(nb, N, 512)`` or ``(0, 0, 0)`` when
    absent, float32; ``valid0 (M,)`` bool. Channels sharing their lights (``scale (nb, G, 512)``,
    else ``(0, 0, 0)``): observation ``k`` (pattern ``k // G``, channel ``g = k % G``) has the
    light ``scale_g L[k // G]``, so ``L`` is ``(nb, P, 3, 512)`` and ``Q`` ``(nb, 1, 6, 512)`` (of
    the unscaled lights): a third of the memory a frame reads. The moments are accumulated over
    pixel-contiguous slices (separate arrays: no aliasing, so the loops vectorise), then every
    pixel is finished from them. Outputs ``normals (M, 3)``, ``albedo (M, G)``, ``residual``,
    ``mask (M,)``."""
    N = obs.shape[0]
    G = num_groups
    has_dark = dark.shape[0] > 0
    has_flat = invflat.shape[0] > 0
    shared = scale.shape[0] > 0
    (r0, r1, r2, S, Ib, t0, t1, t2, bb0, bb1, bb2, n0b, n1b, n2b, mn, okb, rh, a00, a01, a02, a11, a12, a22, Qs) = scratch
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
        o = obs[k, o0:o0 + B]
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
        nrm = np.sqrt(bb0[j] * bb0[j] + bb1[j] * bb1[j] + bb2[j] * bb2[j])
        sc = np.float32(1.0) / max(nrm, _TINY)
        n2 = bb2[j] * sc
        ok = valid0[j0 + j] and nrm > 0 and n2 > 0
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
        x = x0 + j
        ok = okb[j]
        residual[x] = np.sqrt(max(t0[j] - mn[j], np.float32(0.0)) / np.float32(N)) if ok else np.float32(0.0)
        normals[x, 0] = n0b[j]
        normals[x, 1] = n1b[j]
        normals[x, 2] = n2b[j]
        for g in range(G):
            albedo[x, g] = rh[g, j]
        mask[x] = ok


@njit(cache=True, nogil=True, error_model="numpy")
def nearfield_batch(frames, index, channels, dark, invflat, L, inv, Q, scale, groups, num_groups, valid0,
                    iterations, start, stop, normals, albedo, residual, mask):  # pragma: no cover - compiled
    """Pixels ``start:stop`` (``start`` a multiple of 512) of every frame of interleaved camera
    frames ``frames (K, P, H*W*C)`` (``index (M,)``: the solved pixels, empty for all), block by
    block, every frame of a block in turn. Outputs as whole-frame planes (pixels outside
    ``index`` untouched): ``normals (K, 3, H*W)``, ``albedo (K, G, H*W)``, ``residual``, ``mask
    (K, H*W)``."""
    K, P, _ = frames.shape
    N = P * channels
    buf = np.zeros((N, 512), frames.dtype)
    scratch = _nearfield_scratch(num_groups)
    nb = np.empty((512, 3), np.float32)
    ab = np.empty((512, num_groups), np.float32)
    rb = np.empty(512, np.float32)
    mb = np.empty(512, np.bool_)
    for j0 in range(start, stop, 512):
        B = min(stop, j0 + 512) - j0
        for k in range(K):
            gather_block(frames[k], index, j0, B, channels, buf)
            _nearfield_block(buf, 0, B, j0, 0, dark, invflat, L, inv, Q, scale, groups, num_groups, valid0,
                             iterations, scratch, nb, ab, rb, mb)
            _store_block(nb.T, ab.T, rb, mb, index, j0, B, normals[k], albedo[k], residual[k], mask[k])


@njit(nogil=True)
def _store_block(nb, ab, rb, mb, index, j0, B, normals, albedo, residual, mask):  # pragma: no cover - compiled
    """A block's outputs (``nb (3, 512)``, ``ab (G, 512)``, ``rb``, ``mb (512,)``, ``B`` of them
    real) into whole-frame planes ``normals (3, H*W)``, ``albedo (G, H*W)``, ``residual``,
    ``mask (H*W,)`` at pixels ``j0:j0 + B`` (``index[j0:j0 + B]`` when ``index`` is not empty)."""
    whole = index.shape[0] == 0
    for j in range(B):
        x = j0 + j if whole else index[j0 + j]
        residual[x] = rb[j]
        mask[x] = mb[j]
    for c in range(3):
        nc = normals[c]
        bc = nb[c]
        if whole:
            for j in range(B):
                nc[j0 + j] = bc[j]
        else:
            for j in range(B):
                nc[index[j0 + j]] = bc[j]
    for g in range(ab.shape[0]):
        ag = albedo[g]
        bg = ab[g]
        if whole:
            for j in range(B):
                ag[j0 + j] = bg[j]
        else:
            for j in range(B):
                ag[index[j0 + j]] = bg[j]


@njit(inline="always", error_model="numpy", fastmath={"contract"})
def _shared_block(obs, o0, B, j0, x0, dark, invflat, Pi, Q0, scale, U, F, rh, Ib,  # noqa: C901 - compiled: the loop body stays one function so Numba vectorises it
                  normals, albedo, residual, mask):  # pragma: no cover - compiled
    """The block of pixels ``j0:j0 + 512`` (``B`` of them real, ``j0`` a multiple of 512) of
    observation planes ``obs[:, o0:o0 + 512]`` (zero-padded beyond ``B``), pattern-major and
    channel-minor (``N = P G``); outputs at ``x0:x0 + B``.

    Blocked layout (:func:`pipeline.normals.fast.blocked`): ``Pi (nb, P, 3, 512)``, ``Q0 (nb,
    6, 512)`` (xx, xy, xz, yy, yz, zz), ``scale (nb, G, 512)`` (0 at pixels not to solve: the
    validity costs no plane of its own), ``dark``/``invflat`` ``(nb, N, 512)`` or ``(0, 0,
    0)`` when absent, float32. Outputs as planes: ``normals (3, M)``, ``albedo (G, M)``,
    ``residual (M,)`` float32, ``mask (M,)`` bool.

    Every loop over a block's pixels runs the whole 512: with a trip count LLVM knows the loops
    vectorise (measured on one moment's loop: 22 ns a pixel with a computed ``range(B)``, 2
    with ``range(512)``). Per channel its moments (u_x, u_y, u_z, S) in one array ``U (G, 4,
    512)``, and the per-pixel scratch of the finish in another, ``F (10, 512)``: loops that
    store into one array and read few vectorise (each further array costs LLVM runtime
    aliasing checks; measured 9.6 -> 7.1 ns a pixel).
    """
    N = obs.shape[0]
    P = Pi.shape[1]
    G = N // P
    has_dark = dark.shape[0] > 0
    has_flat = invflat.shape[0] > 0
    blk = j0 // 512
    U[:, :, :] = 0.0
    for k in range(N):
        p = k // G
        g = k - p * G
        o = obs[k, o0:o0 + 512]
        Ug = U[g]
        Pp = Pi[blk, p]
        if has_dark or has_flat:
            dk = dark[blk, k] if has_dark else Ib
            fk = invflat[blk, k] if has_flat else Ib
            for j in range(512):
                v = np.float32(o[j])
                if has_dark:
                    v = v - dk[j]
                if has_flat:
                    v = v * fk[j]
                Ib[j] = v
            for j in range(512):
                v = Ib[j]
                Ug[0, j] += v * Pp[0, j]
                Ug[1, j] += v * Pp[1, j]
                Ug[2, j] += v * Pp[2, j]
                Ug[3, j] += v * v
        else:
            for j in range(512):
                v = np.float32(o[j])
                Ug[0, j] += v * Pp[0, j]
                Ug[1, j] += v * Pp[1, j]
                Ug[2, j] += v * Pp[2, j]
                Ug[3, j] += v * v
    F[:4] = 0.0
    for g in range(G):
        sc_ = scale[blk, g]
        Ug = U[g]
        for j in range(512):
            s = sc_[j]
            F[0, j] += s * Ug[0, j]
            F[1, j] += s * Ug[1, j]
            F[2, j] += s * Ug[2, j]
            F[3, j] += s * s
    Qb = Q0[blk]
    for j in range(512):
        # b = A^-1 sum_g r_g up to the positive factor 1 / sum_g s_g^2: the normal is its
        # direction, and its length is not used.
        b0 = F[0, j]
        b1 = F[1, j]
        b2 = F[2, j]
        nrm = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        sc = np.float32(1.0) / max(nrm, _TINY)
        n2 = b2 * sc
        ok = (nrm > 0) & (n2 > 0) & (F[3, j] > 0)  # scale 0: invalid pixel or padding
        n0 = b0 * sc if ok else np.float32(0.0)
        n1 = b1 * sc if ok else np.float32(0.0)
        n2 = n2 if ok else np.float32(1.0)
        F[0, j] = n0
        F[1, j] = n1
        F[2, j] = n2
        F[8, j] = np.float32(1.0) if ok else np.float32(0.0)
        a0 = Qb[0, j] * n0 + Qb[1, j] * n1 + Qb[2, j] * n2  # Q_0 n
        a1 = Qb[1, j] * n0 + Qb[3, j] * n1 + Qb[4, j] * n2
        a2 = Qb[2, j] * n0 + Qb[4, j] * n1 + Qb[5, j] * n2
        F[4, j] = a0
        F[5, j] = a1
        F[6, j] = a2
        F[7, j] = np.float32(1.0) / max(n0 * a0 + n1 * a1 + n2 * a2, _TINY)  # 1 / n^T Q_0 n
        F[9, j] = 0.0
        F[3, j] = 0.0  # now the total energy sum_g S_g
    for g in range(G):
        sc_ = scale[blk, g]
        Ug = U[g]
        rg = rh[g]
        for j in range(512):  # no branch, no division: it vectorises
            w = F[4, j] * Ug[0, j] + F[5, j] * Ug[1, j] + F[6, j] * Ug[2, j]
            wq = w * F[7, j]
            s = sc_[j]
            isc = np.float32(1.0) / s if s > 0 else np.float32(0.0)
            rg[j] = wq * isc * F[8, j]
            F[9, j] += w * wq
            F[3, j] += Ug[3, j]
    # Outputs as planes (contiguous stores; interleaving them here took 6 ns a pixel in
    # scattered stores, cv2.merge does it after in well under one).
    for j in range(B):
        x = x0 + j
        ok = F[8, j] > 0
        residual[x] = np.sqrt(max(F[3, j] - F[9, j], np.float32(0.0)) / np.float32(N)) if ok else np.float32(0.0)
        mask[x] = ok
    for c in range(3):
        nc = normals[c]
        for j in range(B):
            nc[x0 + j] = F[c, j]
    for g in range(G):
        ag = albedo[g]
        for j in range(B):
            ag[x0 + j] = rh[g, j]


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def shared_batch(frames, index, channels, dark, invflat, Pi, Q0, scale, start, stop, normals, albedo, residual,
                 mask):  # pragma: no cover - compiled
    """Pixels ``start:stop`` (``start`` a multiple of 512) of every frame of interleaved camera
    frames ``frames (K, P, H*W*C)`` (``index (M,)``: the solved pixels, empty for all), block by
    block, every frame of a block in turn (its factors stay in cache). Outputs as whole-frame
    planes (pixels outside ``index`` untouched): ``normals (K, 3, H*W)``, ``albedo (K, G, H*W)``,
    ``residual``, ``mask (K, H*W)``."""
    K, P, _ = frames.shape
    N = P * channels
    G = N // Pi.shape[1]
    U = np.empty((G, 4, 512), np.float32)
    F = np.empty((10, 512), np.float32)
    rh = np.empty((G, 512), np.float32)
    Ib = np.empty(512, np.float32)
    buf = np.zeros((N, 512), frames.dtype)
    nb = np.empty((3, 512), np.float32)
    ab = np.empty((G, 512), np.float32)
    rb = np.empty(512, np.float32)
    mb = np.empty(512, np.bool_)
    for j0 in range(start, stop, 512):
        B = min(stop, j0 + 512) - j0
        for k in range(K):
            gather_block(frames[k], index, j0, B, channels, buf)
            _shared_block(buf, 0, B, j0, 0, dark, invflat, Pi, Q0, scale, U, F, rh, Ib, nb, ab, rb, mb)
            _store_block(nb, ab, rb, mb, index, j0, B, normals[k], albedo[k], residual[k], mask[k])
