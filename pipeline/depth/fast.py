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
def _slopes(normals, mask, scale, max_slope, gc, gr, valid):  # pragma: no cover - compiled
    """``pipeline.depth._common.pixel_gradients`` of float32 normals ``(H, W, 3)``: slopes in mm
    per pixel step (``dh/dcol = -n_x / n_z s``, ``dh/drow = n_y / n_z s``), 0 where the mask
    is False or the normal faces away, clipped to ``max_slope``."""
    H, W = mask.shape
    lim = np.float32(max_slope)
    for r in range(H):
        for c in range(W):
            nz = normals[r, c, 2]
            ok = mask[r, c] and nz > 0 and nz < np.inf
            p = np.float32(0.0)
            q = np.float32(0.0)
            if ok:
                p = -normals[r, c, 0] / nz
                q = -normals[r, c, 1] / nz
                ok = np.isfinite(p) and np.isfinite(q)
                if not ok:
                    p = np.float32(0.0)
                    q = np.float32(0.0)
            if abs(p) > lim / np.float32(1.5) or abs(q) > lim / np.float32(1.5):
                mag = np.float32(np.hypot(p, q))
                if mag > lim:
                    f = lim / max(mag, np.float32(1.1754944e-38))
                    p = p * f
                    q = q * f
            gc[r, c] = p * scale
            gr[r, c] = (np.float32(0.0) - q) * scale
            valid[r, c] = ok


@njit(cache=True, nogil=True, error_model="numpy")
def _divergence(gc, gr, f):  # pragma: no cover - compiled
    """``div`` of the edge gradients with the image border's edges taken from the border
    pixels' own slopes (``poisson_dst``'s ``ecp``/``erp`` construction)."""
    H, W = gc.shape
    half = np.float32(0.5)
    for r in range(H):
        for c in range(W):
            right = gc[r, c] if c == W - 1 else half * (gc[r, c + 1] + gc[r, c])
            left = gc[r, c] if c == 0 else half * (gc[r, c] + gc[r, c - 1])
            down = gr[r, c] if r == H - 1 else half * (gr[r + 1, c] + gr[r, c])
            up = gr[r, c] if r == 0 else half * (gr[r, c] + gr[r - 1, c])
            f[r, c] = (right - left) + (down - up)


def dst_divergence(normals, mask, mm_per_px: float, max_slope: float = 20.0):
    """``(f (H, W), valid (H, W))``: the right-hand side of ``poisson_dst``'s Poisson equation
    and its validity mask, from float32 unit normals ``(H, W, 3)`` and ``mask (H, W)``."""
    n = np.ascontiguousarray(normals, np.float32)
    m = np.ascontiguousarray(mask, np.bool_)
    H, W = m.shape
    gc = np.empty((H, W), np.float32)
    gr = np.empty((H, W), np.float32)
    valid = np.empty((H, W), np.bool_)
    _slopes(n, m, np.float32(mm_per_px), np.float32(max_slope), gc, gr, valid)
    f = np.empty((H, W), np.float32)
    _divergence(gc, gr, f)
    return f, valid


class FastDST:
    """DST Poisson integration for frames of one size (eigenvalues kept).

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
        from pipeline.depth.poisson import _dst_eigenvalues

        self.shape = (int(shape[0]), int(shape[1]))
        self.mm_per_px = float(mm_per_px)
        self.max_slope = float(max_slope)
        self.workers = int(workers)
        self.eig = _dst_eigenvalues(*self.shape).astype(np.float32)

    def integrate(self, normals, mask=None, workers: int | None = None) -> DepthResult:
        """Heights ``(H, W)`` mm of float32 normals ``(H, W, 3)``; ``mask`` the valid ones."""
        m = np.ones(self.shape, bool) if mask is None else mask
        f, valid = dst_divergence(normals, m, self.mm_per_px, self.max_slope)
        w = self.workers if workers is None else int(workers)
        F = scipy.fft.dstn(f, type=2, workers=w)
        h = scipy.fft.idstn(F / self.eig, type=2, workers=w)
        return DepthResult(height=h.astype(np.float32, copy=False), mask=valid,
                           meta={"integrator": "dst", "method": "fast", "mm_per_px": self.mm_per_px,
                                 "max_slope": self.max_slope})
