"""Masked least-squares integration: only valid pixels are unknowns, only edges between two
valid pixels are equations; solved by preconditioned conjugate gradients (scipy.sparse).

On a non-rectangular object (a DiLiGenT silhouette, a contact region with masked holes) the
rectangle solvers must invent gradients outside the mask and their error is dominated by it;
this solver never looks outside.
"""

from __future__ import annotations

import numpy as np
import scipy.fft
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from pipeline.depth._common import DepthResult, anchor_to_border, half_pixel_gradients, pixel_gradients
from pipeline.depth.poisson import dct_poisson_solve, neumann_eigenvalues

__all__ = ["sparse_lstsq"]


def _edge_system(m: np.ndarray, gc: np.ndarray, gr: np.ndarray):
    """Incidence matrix ``D`` (edges x unknowns) and edge targets for the valid pixels."""
    H, W = m.shape
    idx = -np.ones((H, W), dtype=np.int64)
    idx[m] = np.arange(int(m.sum()))
    ec, er = half_pixel_gradients(gc, gr)
    hc = m[:, :-1] & m[:, 1:]
    vr = m[:-1, :] & m[1:, :]
    a = np.concatenate([idx[:, :-1][hc], idx[:-1, :][vr]])
    b = np.concatenate([idx[:, 1:][hc], idx[1:, :][vr]])
    target = np.concatenate([ec[hc], er[vr]])
    e = len(a)
    rows = np.concatenate([np.arange(e), np.arange(e)])
    cols = np.concatenate([b, a])
    vals = np.concatenate([np.ones(e), -np.ones(e)])
    D = sp.csr_matrix((vals, (rows, cols)), shape=(e, int(m.sum())))
    return D, target, idx


def _dct_heights(gc, gr) -> np.ndarray:
    from pipeline.depth._common import divergence_neumann

    return dct_poisson_solve(divergence_neumann(gc, gr))


def _dct_preconditioner(m: np.ndarray, eps: float) -> spla.LinearOperator:
    """``r -> (P^T (-lap_N)^+ P) r`` with the constant mode scaled by ``1 / (N eps + 1)``:
    SPD, and the exact inverse of the system when the mask is the full rectangle."""
    H, W = m.shape
    lam = -neumann_eigenvalues(H, W)
    lam[0, 0] = 1.0
    inv = 1.0 / (lam + eps)
    inv[0, 0] = 1.0 / (eps * m.size + 1.0)
    n = int(m.sum())

    def apply(r):
        full = np.zeros((H, W))
        full[m] = r
        F = scipy.fft.dctn(full, type=2, norm="ortho")
        return scipy.fft.idctn(F * inv, type=2, norm="ortho")[m]

    return spla.LinearOperator((n, n), matvec=apply, dtype=np.float64)


def sparse_lstsq(normals, mm_per_px: float, mask=None, *, max_slope: float = 20.0, rtol: float = 1e-8,
                 maxiter: int = 2000, regularization: float = 1e-8) -> DepthResult:
    """Height map by least squares over the valid pixels only.

    Parameters
    ----------
    normals : ndarray, shape (H, W, 3)
    mm_per_px : float
    mask : ndarray, shape (H, W), bool, optional
        Pixels to integrate (default: all with finite, camera-facing normals).
    rtol, maxiter : float, int
        Conjugate-gradient tolerance and iteration cap.
    regularization : float
        A tiny ``eps * I`` (relative to the Laplacian's diagonal) that pins the free constant of
        each connected piece of the mask, so the system is positive definite.

    Returns
    -------
    DepthResult
        Heights (mm) on the mask, 0 elsewhere; anchored so the median over valid border
        pixels is 0. ``meta["iterations"]`` and ``meta["converged"]`` report the CG run.

    Notes
    -----
    Preconditioner: the inverse of the full-rectangle Neumann Laplacian by DCT, restricted to
    the mask (symmetric positive definite; exact when the mask is the whole image, so CG then
    converges at once, and close wherever the mask is large). Start: the DCT Poisson solution.

    Examples
    --------
    An L-shaped mask over a plane: exact on the mask, zero off it.

    >>> from pipeline.base.frames import gradients_to_normals
    >>> n = gradients_to_normals(np.full((4, 4), 1.0), np.zeros((4, 4)))
    >>> m = np.ones((4, 4), bool); m[:2, 2:] = False
    >>> out = sparse_lstsq(n, 1.0, m)
    >>> np.round(out.height, 6).tolist()[3], np.round(out.height, 6).tolist()[0][3]
    ([-1.0, 0.0, 1.0, 2.0], 0.0)
    """
    gc, gr, m = pixel_gradients(normals, mask, mm_per_px, max_slope, "sparse_lstsq")
    gc, gr = gc.astype(np.float64), gr.astype(np.float64)  # CG in float64
    H, W = gc.shape
    height = np.zeros((H, W))
    n = int(m.sum())
    iterations, converged = 0, True
    if n:
        D, target, idx = _edge_system(m, gc, gr)
        A = (D.T @ D).tocsr()
        diag = A.diagonal()
        eps = regularization * max(float(diag.mean()), 1.0)
        A = A + eps * sp.identity(n, format="csr")
        rhs = D.T @ target
        M = _dct_preconditioner(m, eps)
        x0 = _dct_heights(gc, gr)[m]
        x0 -= x0.mean()
        counter = {"it": 0}

        def count(_):
            counter["it"] += 1

        x, info = spla.cg(A, rhs, x0=x0, rtol=rtol, atol=0.0, maxiter=maxiter, M=M, callback=count)
        iterations, converged = counter["it"], info == 0
        height[m] = np.where(np.isfinite(x), x, 0.0)
        height = np.where(m, anchor_to_border(height, m), 0.0)
    return DepthResult(height=height.astype(np.float32), mask=m,
                       meta={"integrator": "sparse", "mm_per_px": float(mm_per_px), "max_slope": float(max_slope),
                             "iterations": int(iterations), "converged": bool(converged)})
