"""The live DST integrator: the same Poisson solve as :func:`pipeline.depth.poisson.poisson_dst`,
with its per-frame set-up fused into one compiled pass.

``poisson_dst`` builds the divergence of the edge gradients with about fifteen whole-image
numpy operations (normals to slopes, masking, clipping, half-pixel averages, the border
edges, the differences); at 320 x 240 they cost more than the two float32 transforms
themselves. :func:`dst_divergence` computes the same ``f (H, W)`` in one Numba pass (cached on
disk), and :class:`FastDST` keeps the eigenvalues of the size. The transforms are the same
``scipy.fft.dstn``/``idstn`` calls, so heights agree with ``poisson_dst`` to float32 rounding
(``tests/pipeline/normals/test_fast_paths.py``).
"""

from __future__ import annotations

import numpy as np
import scipy.fft
from numba import njit

from pipeline.depth._common import DepthResult

__all__ = ["FastDST", "dst_divergence"]


@njit(cache=True, nogil=True, error_model="numpy")
def _divergence_planes(nx, ny, nz, mask, scale, max_slope, f, valid):  # pragma: no cover - compiled
    """``pipeline.depth._common.pixel_gradients`` of float32 normal planes ``(H, W)`` each, then
    ``poisson_dst``'s divergence of the edge gradients, a row at a time.

    Slopes in mm per pixel step (``dh/dcol = -n_x / n_z s``, ``dh/drow = n_y / n_z s``), 0
    where the mask is False or the normal faces away, clipped to ``max_slope``; the image
    border's edges are the border pixels' own slopes (``poisson_dst``'s ``ecp``/``erp``).
    Written without branches on planes (reading ``(H, W, 3)`` normals took a gather per pixel
    and the branches kept the loops scalar: 0.28 -> under 0.1 ms at 320 x 240).
    """
    H, W = mask.shape
    lim = np.float32(max_slope)
    zero = np.float32(0.0)
    half = np.float32(0.5)
    gc = np.empty((3, W), np.float32)  # rows r-1, r, r+1 of the column slopes, cyclically
    gr = np.empty((3, W), np.float32)
    for r in range(-1, H):
        if r + 1 < H:
            rr = r + 1
            dc = gc[rr % 3]
            dr = gr[rr % 3]
            x = nx[rr]
            y = ny[rr]
            z = nz[rr]
            m = mask[rr]
            v = valid[rr]
            for c in range(W):
                n2 = z[c]
                ok = m[c] & (n2 > 0) & (n2 < np.inf)
                p = -x[c] / n2
                q = -y[c] / n2
                ok = ok & (p - p == 0) & (q - q == 0)  # finite
                p = p if ok else zero
                q = q if ok else zero
                mag = np.sqrt(p * p + q * q)
                k = lim / max(mag, np.float32(1.1754944e-38))
                k = k if mag > lim else np.float32(1.0)
                dc[c] = p * k * scale
                dr[c] = (zero - q * k) * scale
                v[c] = ok
        if r < 0:
            continue
        cur_c = gc[r % 3]
        cur_r = gr[r % 3]
        up_r = gr[(r - 1) % 3] if r > 0 else cur_r
        dn_r = gr[(r + 1) % 3] if r < H - 1 else cur_r
        fr = f[r]
        for c in range(1, W - 1):
            fr[c] = (half * (cur_c[c + 1] - cur_c[c - 1])
                     + (half * (dn_r[c] + cur_r[c]) if r < H - 1 else cur_r[c])
                     - (half * (cur_r[c] + up_r[c]) if r > 0 else cur_r[c]))
        for c in (0, W - 1):
            right = cur_c[c] if c == W - 1 else half * (cur_c[c + 1] + cur_c[c])
            left = cur_c[c] if c == 0 else half * (cur_c[c] + cur_c[c - 1])
            down = cur_r[c] if r == H - 1 else half * (dn_r[c] + cur_r[c])
            up = cur_r[c] if r == 0 else half * (cur_r[c] + up_r[c])
            fr[c] = (right - left) + (down - up)


@njit(cache=True, nogil=True, error_model="numpy")
def _divergence_batch(normals, last, mask, scale, max_slope, k0, k1, f, valid):  # pragma: no cover - compiled
    """:func:`_divergence_planes` of frames ``k0:k1`` into ``f[k - k0]`` and ``valid[k]``: normal
    planes ``(K, 3, H, W)``, or with ``last`` normals ``(K, H, W, 3)`` (read strided)."""
    for k in range(k0, k1):
        if last:
            _divergence_planes(normals[k, :, :, 0], normals[k, :, :, 1], normals[k, :, :, 2], mask[k], scale,
                               max_slope, f[k - k0], valid[k])
        else:
            _divergence_planes(normals[k, 0], normals[k, 1], normals[k, 2], mask[k], scale, max_slope, f[k - k0],
                               valid[k])


@njit(cache=True, nogil=True, error_model="numpy")
def _divide(F, eig):  # pragma: no cover - compiled
    """``F[k] /= eig`` for every frame of ``F (K, H, W)`` (numpy's broadcast division, without
    its lock and its temporary)."""
    for k in range(F.shape[0]):
        Fk = F[k]
        for r in range(F.shape[1]):
            a = Fk[r]
            e = eig[r]
            for c in range(F.shape[2]):
                a[c] = a[c] / e[c]


def dst_divergence(normals, mask, mm_per_px: float, max_slope: float = 20.0):
    """``(f (H, W), valid (H, W))``: the right-hand side of ``poisson_dst``'s Poisson equation
    and its validity mask, from float32 unit normals ``(H, W, 3)`` and ``mask (H, W)``."""
    import cv2

    m = np.ascontiguousarray(mask, np.bool_)
    H, W = m.shape
    planes = np.moveaxis(np.asarray(normals), -1, 0)
    if planes.dtype == np.float32 and planes.flags.c_contiguous:
        nx, ny, nz = planes  # the fast near-field path's normals are a view of its planes
    else:
        nx, ny, nz = cv2.split(np.ascontiguousarray(normals, np.float32))  # planes: the loops vectorise
    f = np.empty((H, W), np.float32)
    valid = np.empty((H, W), np.bool_)
    _divergence_planes(nx, ny, nz, m, np.float32(mm_per_px), np.float32(max_slope), f, valid)
    return f, valid


class FastDST:
    """DST Poisson integration for frames of one size (eigenvalues kept): the ``dst``
    integrator's registered fast path (:func:`pipeline.depth.frame_integrator`).

    Parameters
    ----------
    shape : (H, W)
    mm_per_px : float
    max_slope : float
    workers : int
        Threads of the transforms (``scipy.fft`` ``workers``).

    Examples
    --------
    >>> from pipeline.base.frames import normals_from_height
    >>> yy, xx = np.mgrid[0:32, 0:32]
    >>> h = 0.3 * np.exp(-((xx - 15.5) ** 2 + (yy - 15.5) ** 2) / 40.0)
    >>> out = FastDST((32, 32), 0.1).integrate(normals_from_height(h, 0.1).astype(np.float32))
    >>> bool(np.abs(out.height - h).max() < 0.01)
    True
    """

    def __init__(self, shape, mm_per_px: float, max_slope: float = 20.0, workers: int = 1):
        from pipeline.depth.poisson import dst_eigenvalues

        self.shape = (int(shape[0]), int(shape[1]))
        self.mm_per_px = float(mm_per_px)
        self.max_slope = float(max_slope)
        self.workers = int(workers)
        self.eig = dst_eigenvalues(*self.shape).astype(np.float32)
        self.method = "fast"

    def integrate(self, normals, mask=None, workers: int | None = None) -> DepthResult:
        """Heights ``(H, W)`` mm of float32 normals ``(H, W, 3)``; ``mask`` the valid ones."""
        m = np.ones(self.shape, bool) if mask is None else mask
        f, valid = dst_divergence(normals, m, self.mm_per_px, self.max_slope)
        w = self.workers if workers is None else int(workers)
        F = scipy.fft.dstn(f, type=2, workers=w)
        h = scipy.fft.idstn(F / self.eig, type=2, workers=w)
        return DepthResult(height=h.astype(np.float32, copy=False), mask=valid, meta=self.meta())

    def meta(self) -> dict:
        return {"integrator": "dst", "method": "fast", "mm_per_px": self.mm_per_px, "max_slope": self.max_slope}

    def integrate_batch(self, normals, mask, pool=None, out=None, parts: int | None = None):
        """``(height (K, H, W), valid (K, H, W))`` of float32 normal planes ``normals (K, 3, H, W)``
        (:class:`pipeline.normals.fast.PlaneBatch`; or normals ``(K, H, W, 3)``, read strided)
        and ``mask (K, H, W)``: the same numbers as :meth:`integrate` frame by frame.

        ``pool``: a :class:`pipeline.base.frame_pool.FramePool` whose threads take ``parts``
        (default one a thread) contiguous runs of frames, each run one divergence call, one
        ``scipy.fft.dstn`` and one ``idstn`` over the run (transforms of one thread: the
        threads are the pool's); None: this thread. ``out``: ``(height, valid)`` arrays to fill.
        """
        n = np.ascontiguousarray(normals, np.float32)
        m = np.ascontiguousarray(mask, np.bool_)
        K = n.shape[0]
        H, W = self.shape
        last = n.shape != (K, 3, H, W) and n.shape == (K, H, W, 3)
        if n.shape != (K, 3, H, W) and not last:
            raise ValueError(f"FastDST.integrate_batch: normals must be planes (K, 3, {H}, {W}) or (K, {H}, {W}, 3), "
                             f"got {n.shape}")
        if m.shape != (K, H, W):
            raise ValueError(f"FastDST.integrate_batch: mask must be ({K}, {H}, {W}), got {m.shape}")
        height, valid = out if out is not None else (np.empty((K, H, W), np.float32), np.empty((K, H, W), np.bool_))
        if height.shape != (K, H, W) or valid.shape != (K, H, W) or valid.dtype != np.bool_:
            raise ValueError(f"FastDST.integrate_batch: out must be float32 heights and a bool mask ({K}, {H}, {W}), "
                             f"got {height.shape} {height.dtype}, {valid.shape} {valid.dtype}")
        in_place = height.dtype == np.float32 and height.flags.c_contiguous

        def run(k0: int, k1: int) -> None:
            # The run's heights are its working memory: divergence, DST, division, inverse DST
            # all in place (scipy.fft transforms a contiguous float32 array in place with
            # overwrite_x), so the run's frames are read once and written once.
            f = height[k0:k1] if in_place else np.empty((k1 - k0, H, W), np.float32)
            _divergence_batch(n, last, m, np.float32(self.mm_per_px), np.float32(self.max_slope), k0, k1, f, valid)
            F = scipy.fft.dstn(f, type=2, axes=(1, 2), workers=1, overwrite_x=True)
            _divide(F, self.eig)
            h = scipy.fft.idstn(F, type=2, axes=(1, 2), workers=1, overwrite_x=True)
            if not (in_place and np.may_share_memory(h, f)):
                height[k0:k1] = h

        if pool is None:
            run(0, K)
        else:
            pool.split(run, K, parts=parts)
        return height, valid
