"""Poisson integration by fast cosine / sine transforms on the full rectangle.

Both solve the least-squares problem over pixel edges (see :mod:`pipeline.depth._common`):
``lap h = div g`` with the 5-point Laplacian.

- :func:`poisson_dct`: Neumann border (no edge leaves the image); the DCT-II diagonalises it.
  Exact for any integrable field up to a constant.
- :func:`poisson_dst`: Dirichlet border: the outermost pixels hold given heights (zero by
  default: the gel is flat away from contact) and the interior is solved by a DST-I.
"""

from __future__ import annotations

import numpy as np
import scipy.fft

from pipeline.depth._common import (DepthResult, anchor_to_border, divergence_neumann, half_pixel_gradients,
                                    pixel_gradients)

__all__ = ["poisson_dct", "poisson_dst"]


def poisson_dct(normals, mm_per_px: float, mask=None, *, max_slope: float = 20.0,
                workers: int | None = None) -> DepthResult:
    """Height map by the DCT Poisson solver (Neumann border).

    Parameters and return as :func:`pipeline.depth.frankot_chellappa`; heights are anchored
    so the median over the image border is 0.

    Examples
    --------
    A plane is recovered exactly:

    >>> from sim.frames import gradients_to_normals
    >>> n = gradients_to_normals(np.full((4, 5), 0.5), np.zeros((4, 5)))
    >>> np.round(poisson_dct(n, 1.0).height[0], 6).tolist()
    [-1.0, -0.5, 0.0, 0.5, 1.0]
    """
    gc, gr, m = pixel_gradients(normals, mask, mm_per_px, max_slope, "poisson_dct")
    H, W = gc.shape
    f = divergence_neumann(gc, gr)
    F = scipy.fft.dctn(f, type=2, norm="ortho", workers=workers)
    lam = (2.0 * np.cos(np.pi * np.arange(H) / H) - 2.0)[:, None] + (2.0 * np.cos(np.pi * np.arange(W) / W) - 2.0)[None, :]
    lam[0, 0] = 1.0
    F = F / lam
    F[0, 0] = 0.0
    h = scipy.fft.idctn(F, type=2, norm="ortho", workers=workers)
    h = anchor_to_border(h, m)
    return DepthResult(height=h.astype(np.float32), mask=m,
                       meta={"integrator": "dct", "mm_per_px": float(mm_per_px), "max_slope": float(max_slope)})


def poisson_dst(normals, mm_per_px: float, mask=None, *, boundary=None, max_slope: float = 20.0,
                workers: int | None = None) -> DepthResult:
    """Height map by the DST Poisson solver (given heights on the outermost pixels).

    Parameters
    ----------
    boundary : ndarray, shape (H, W), optional
        Heights (mm) whose outermost ring is imposed; default zero (flat gel at the border).
    Others as :func:`poisson_dct`.

    Examples
    --------
    A bump that is flat at the border is recovered:

    >>> from sim.frames import normals_from_height
    >>> yy, xx = np.mgrid[0:32, 0:32]
    >>> h = 0.3 * np.exp(-((xx - 15.5) ** 2 + (yy - 15.5) ** 2) / 40.0)
    >>> out = poisson_dst(normals_from_height(h, 0.1), 0.1)
    >>> bool(np.abs(out.height - h).max() < 0.01), float(out.height[0, 0])
    (True, 0.0)
    """
    gc, gr, m = pixel_gradients(normals, mask, mm_per_px, max_slope, "poisson_dst")
    H, W = gc.shape
    full = np.zeros((H, W))
    if boundary is not None:
        b = np.asarray(boundary, dtype=np.float64)
        if b.shape != (H, W):
            raise ValueError(f"poisson_dst: boundary must have shape {(H, W)}, got {b.shape}")
        ring = np.ones((H, W), bool)
        ring[1:-1, 1:-1] = False
        full[ring] = np.nan_to_num(b[ring], nan=0.0, posinf=0.0, neginf=0.0)
    if H >= 3 and W >= 3:
        ec, er = half_pixel_gradients(gc, gr)
        f = (ec[1:-1, 1:] - ec[1:-1, :-1]) + (er[1:, 1:-1] - er[:-1, 1:-1])
        # Known border heights move to the right-hand side (the interior of `full` is still 0).
        f = f - (full[1:-1, 2:] + full[1:-1, :-2] + full[2:, 1:-1] + full[:-2, 1:-1])
        h_in, w_in = H - 2, W - 2
        F = scipy.fft.dstn(f, type=1, workers=workers)
        lam = ((2.0 * np.cos(np.pi * np.arange(1, h_in + 1) / (h_in + 1)) - 2.0)[:, None]
               + (2.0 * np.cos(np.pi * np.arange(1, w_in + 1) / (w_in + 1)) - 2.0)[None, :])
        full[1:-1, 1:-1] = scipy.fft.idstn(F / lam, type=1, workers=workers)
    return DepthResult(height=full.astype(np.float32), mask=m,
                       meta={"integrator": "dst", "mm_per_px": float(mm_per_px), "max_slope": float(max_slope)})
