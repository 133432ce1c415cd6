"""Poisson integration by fast cosine / sine transforms on the full rectangle.

Both solve the least-squares problem over pixel edges (see :mod:`pipeline.depth._common`):
``lap h = div g`` with the 5-point Laplacian.

- :func:`poisson_dct`: Neumann border (no edge leaves the image); the DCT-II diagonalises it.
  Exact for any integrable field up to a constant.
- :func:`poisson_dst`: Dirichlet border: zero height at the image edge (the gel is flat away
  from contact), solved by a DST-II/III pair.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.fft

from pipeline.depth._common import (
    DepthResult,
    anchor_to_border,
    divergence_neumann,
    half_pixel_gradients,
    pixel_gradients,
)

__all__ = ["poisson_dct", "poisson_dst", "dst_eigenvalues"]


@lru_cache(maxsize=16)
def _neumann_eigenvalues(H: int, W: int) -> np.ndarray:
    lam = neumann_eigenvalues(H, W)
    lam[0, 0] = 1.0
    return lam


def neumann_eigenvalues(H: int, W: int) -> np.ndarray:
    """Eigenvalues ``(H, W)`` of the 5-point Neumann Laplacian in the DCT-II basis (``[0, 0] = 0``)."""
    return ((2.0 * np.cos(np.pi * np.arange(H) / H) - 2.0)[:, None]
            + (2.0 * np.cos(np.pi * np.arange(W) / W) - 2.0)[None, :])


def dct_poisson_solve(f: np.ndarray, workers: int | None = None) -> np.ndarray:
    """Solve ``lap_N h = f`` ``(H, W)`` (Neumann), the free constant set to mean zero."""
    H, W = f.shape
    F = scipy.fft.dctn(f, type=2, norm="ortho", workers=workers)
    F = F / _neumann_eigenvalues(H, W).astype(f.dtype, copy=False)
    F[0, 0] = 0.0
    return scipy.fft.idctn(F, type=2, norm="ortho", workers=workers)


def poisson_dct(normals, mm_per_px: float, mask=None, *, max_slope: float = 20.0,
                workers: int | None = None) -> DepthResult:
    """Height map by the DCT Poisson solver (Neumann border).

    Parameters and return as :func:`pipeline.depth.frankot_chellappa`; heights are anchored
    so the median over the image border is 0.

    Examples
    --------
    A plane is recovered exactly:

    >>> from pipeline.base.frames import gradients_to_normals
    >>> n = gradients_to_normals(np.full((4, 5), 0.5), np.zeros((4, 5)))
    >>> np.round(poisson_dct(n, 1.0).height[0], 6).tolist()
    [-1.0, -0.5, 0.0, 0.5, 1.0]
    """
    gc, gr, m = pixel_gradients(normals, mask, mm_per_px, max_slope, "poisson_dct")
    h = anchor_to_border(dct_poisson_solve(divergence_neumann(gc, gr), workers), m)
    return DepthResult(height=h.astype(np.float32), mask=m,
                       meta={"integrator": "dct", "mm_per_px": float(mm_per_px), "max_slope": float(max_slope)})


@lru_cache(maxsize=16)
def dst_eigenvalues(H: int, W: int) -> np.ndarray:
    """Eigenvalues of the 5-point Laplacian with zero height half a pixel outside the image,
    in the DST-II basis ``sin(pi k (j + 1/2) / N)``, ``k = 1..N``."""
    ky = 2.0 * np.cos(np.pi * np.arange(1, H + 1) / H) - 2.0
    kx = 2.0 * np.cos(np.pi * np.arange(1, W + 1) / W) - 2.0
    return ky[:, None] + kx[None, :]


def poisson_dst(normals, mm_per_px: float, mask=None, *, boundary=None, max_slope: float = 20.0,
                workers: int | None = None) -> DepthResult:
    """Height map by the DST Poisson solver: zero height at the image edge.

    The Dirichlet boundary sits at the image edge, half a pixel outside the outermost pixel
    centres (the DST-II/III pair: transform lengths ``2H``, ``2W``, which stay fast for the
    usual even sizes, unlike DST-I's ``2(H-1)``). The gel is flat away from contact, so this
    is the tactile sensor's natural boundary: no offset to choose.

    Parameters
    ----------
    boundary : ndarray, shape (H, W), optional
        A height field whose values at the image edge are imposed instead of zero (the
        solve is for ``h - boundary`` with zero edge values); a plane given as its own
        boundary comes out exact.
    Others as :func:`poisson_dct`.

    Examples
    --------
    A bump that is flat at the border is recovered:

    >>> from pipeline.base.frames import normals_from_height
    >>> yy, xx = np.mgrid[0:32, 0:32]
    >>> h = 0.3 * np.exp(-((xx - 15.5) ** 2 + (yy - 15.5) ** 2) / 40.0)
    >>> out = poisson_dst(normals_from_height(h, 0.1), 0.1)
    >>> bool(np.abs(out.height - h).max() < 0.01), bool(abs(out.height[0, 0]) < 1e-3)
    (True, True)
    """
    gc, gr, m = pixel_gradients(normals, mask, mm_per_px, max_slope, "poisson_dst")
    H, W = gc.shape
    ec, er = half_pixel_gradients(gc, gr)
    # Edges through the image border (pixel centre to the zero-height edge and beyond):
    # the border pixels' own slopes.
    left, right, top, bottom = gc[:, :1], gc[:, -1:], gr[:1, :], gr[-1:, :]
    B = None
    if boundary is not None:
        B = np.asarray(boundary, dtype=gc.dtype)
        if B.shape != (H, W):
            raise ValueError(f"poisson_dst: boundary must have shape {(H, W)}, got {B.shape}")
        B = np.nan_to_num(B, nan=0.0, posinf=0.0, neginf=0.0)
        ec = ec - np.diff(B, axis=1)
        er = er - np.diff(B, axis=0)
        if W > 1:
            left, right = left - (B[:, 1:2] - B[:, :1]), right - (B[:, -1:] - B[:, -2:-1])
        if H > 1:
            top, bottom = top - (B[1:2] - B[:1]), bottom - (B[-1:] - B[-2:-1])
    ecp = np.concatenate([left, ec, right], axis=1)  # (H, W + 1)
    erp = np.concatenate([top, er, bottom], axis=0)  # (H + 1, W)
    f = (ecp[:, 1:] - ecp[:, :-1]) + (erp[1:, :] - erp[:-1, :])
    F = scipy.fft.dstn(f, type=2, workers=workers)
    h = scipy.fft.idstn(F / dst_eigenvalues(H, W).astype(f.dtype, copy=False), type=2, workers=workers)
    if B is not None:
        h = h + B
    return DepthResult(height=h.astype(np.float32), mask=m,
                       meta={"integrator": "dst", "mm_per_px": float(mm_per_px), "max_slope": float(max_slope)})
