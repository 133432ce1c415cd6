"""The near-field kernel for channels that share their lights (white patterns), in pseudo-inverse form.

Why a second kernel: with white patterns every camera channel sees the same LEDs, so the light
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

__all__ = ["shared_factors"]

_TINY = np.float32(1.1754944e-38)


def shared_factors(L0: np.ndarray, Q0: np.ndarray, invertible: np.ndarray):
    """``Pi (P, M, 3)`` float64: ``Q_0^-1 L_p`` per pixel (0 where ``Q_0`` is singular), from the
    first channel's lights ``L0 (P, M, 3)`` and their Gram matrices ``Q0 (M, 3, 3)``."""
    inv = np.zeros_like(Q0)
    inv[invertible] = np.linalg.inv(Q0[invertible])
    return np.einsum("mij,pmj->pmi", inv, L0)


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def shared_kernel(obs, dark, invflat, Pi, Q0, scale, start, stop,  # noqa: C901 - compiled: the loop body stays one function so Numba vectorises it
                  normals, albedo, residual, mask):  # pragma: no cover - compiled
    """Pixels ``start:stop`` (``start`` a multiple of 512) of observation planes ``obs (N, M)``
    (pattern-major, channel-minor, ``N = P G``).

    Blocked layout (``pipeline.normals.fast._blocked``): ``Pi (nb, P, 3, 512)``, ``Q0 (nb, 6,
    512)`` (xx, xy, xz, yy, yz, zz), ``scale (nb, G, 512)`` (0 at pixels not to solve: the
    validity costs no plane of its own), ``dark``/``invflat`` ``(nb, N, 512)`` or ``(0, 0,
    0)`` when absent, float32. Outputs as planes: ``normals (3, M)``, ``albedo (G, M)``,
    ``residual (M,)`` float32, ``mask (M,)`` bool.

    Every loop over a block's pixels runs the whole 512 (a short last block is zero-padded
    into ``tail``): with a trip count LLVM knows the loops vectorise (measured on one moment's
    loop: 22 ns a pixel with a computed ``range(B)``, 2 with ``range(512)``).
    """
    N = obs.shape[0]
    P = Pi.shape[1]
    G = N // P
    has_dark = dark.shape[0] > 0
    has_flat = invflat.shape[0] > 0
    # Per channel its moments (u_x, u_y, u_z, S) in one array, and the per-pixel scratch of
    # the finish in another: loops that store into one array and read few vectorise (each
    # further array costs LLVM runtime aliasing checks; measured 9.6 -> 7.1 ns a pixel).
    U = np.empty((G, 4, 512), np.float32)
    F = np.empty((10, 512), np.float32)  # b (3), sum s^2, Q_0 n (3), n^T Q_0 n, ok, explained
    rh = np.empty((G, 512), np.float32)
    Ib = np.empty(512, np.float32)
    tail = np.zeros((N, 512), obs.dtype)
    for j0 in range(start, stop, 512):
        B = min(stop, j0 + 512) - j0
        blk = j0 // 512
        if B < 512:
            for k in range(N):
                for j in range(B):
                    tail[k, j] = obs[k, j0 + j]
        U[:, :, :] = 0.0
        for k in range(N):
            p = k // G
            g = k - p * G
            o = obs[k, j0:j0 + 512] if B == 512 else tail[k]
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
            x = j0 + j
            ok = F[8, j] > 0
            residual[x] = np.sqrt(max(F[3, j] - F[9, j], np.float32(0.0)) / np.float32(N)) if ok else np.float32(0.0)
            mask[x] = ok
        for c in range(3):
            nc = normals[c]
            for j in range(B):
                nc[j0 + j] = F[c, j]
        for g in range(G):
            ag = albedo[g]
            for j in range(B):
                ag[j0 + j] = rh[g, j]
