"""A per-bin position correction for the lookup table (Taxim keeps a quadratic in x, y per bin).

The same colour change means a different tilt in different parts of the image when the
lighting is uneven. Instead of one gradient per colour bin, each bin holds a polynomial in
the normalised pixel position ``(u, v)`` (:func:`calibration.models.nearfield.poly_terms`):
``g(d, u, v) = sum_t c_t(bin(d)) phi_t(u, v)``. Each bin's coefficients are a ridge-damped
least-squares fit over the samples in it; the moment sums are smoothed across bins with the
same Gaussian as the table (neighbouring colours share data), and the position terms are
damped toward zero (``ridge`` x the bin's sample count) so that a bin seen at one place only
falls back to its average. Empty bins copy the nearest measured bin's coefficients.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_position_coefficients", "evaluate_position_coefficients"]


def fit_position_coefficients(flat_index: np.ndarray, bins: int, phi: np.ndarray, gradients: np.ndarray,
                              smooth_bins: float = 1.0, ridge: float = 0.005) -> np.ndarray:
    """Per-bin coefficients ``(B, B, B, T, 2)`` of gradients on position terms.

    Parameters
    ----------
    flat_index : ndarray, shape (N,), int
        Each sample's bin (``np.ravel_multi_index`` over ``(B, B, B)``).
    bins : int
    phi : ndarray, shape (N, T)
        Position terms (first column 1).
    gradients : ndarray, shape (N, 2)
    smooth_bins, ridge : float

    Examples
    --------
    One bin, gradient exactly linear in u: recovered.

    >>> u = np.linspace(-1, 1, 50); phi = np.stack([np.ones(50), u, u * 0], 1)
    >>> g = np.stack([0.2 + 0.1 * u, -0.3 * np.ones(50)], 1)
    >>> c = fit_position_coefficients(np.zeros(50, int), 2, phi, g, smooth_bins=0, ridge=0.0)
    >>> (np.round(c[0, 0, 0], 6) + 0.0).tolist()
    [[0.2, -0.3], [0.1, 0.0], [0.0, 0.0]]
    """
    from scipy import ndimage  # here: a live start loads this module, never fits (docs/live.md)

    n_bins = bins ** 3
    t = phi.shape[1]
    # Moments per bin: phi phi^T (T x T) and phi g (T x 2), as bin-count channels.
    A = np.zeros((t, t, n_bins))
    b = np.zeros((t, 2, n_bins))
    for i in range(t):
        for j in range(i, t):
            A[i, j] = A[j, i] = np.bincount(flat_index, phi[:, i] * phi[:, j], minlength=n_bins)
        for k in range(2):
            b[i, k] = np.bincount(flat_index, phi[:, i] * gradients[:, k], minlength=n_bins)
    measured = A[0, 0] > 0
    shape3 = (bins,) * 3
    if smooth_bins > 0:
        A = np.stack([[ndimage.gaussian_filter(A[i, j].reshape(shape3), smooth_bins, mode="constant").ravel()
                       for j in range(t)] for i in range(t)])
        b = np.stack([[ndimage.gaussian_filter(b[i, k].reshape(shape3), smooth_bins, mode="constant").ravel()
                       for k in range(2)] for i in range(t)])
    A = np.moveaxis(A, -1, 0)  # (n_bins, T, T)
    b = np.moveaxis(b, -1, 0)  # (n_bins, T, 2)
    damp = np.eye(t)
    damp[0, 0] = 0.0
    coef = np.zeros((n_bins, t, 2))
    m = np.nonzero(measured)[0]
    if len(m):
        Am = A[m] + ridge * A[m, 0, 0][:, None, None] * damp + 1e-12 * np.eye(t)
        coef[m] = np.linalg.solve(Am, b[m])
    # Empty bins: the nearest measured bin's coefficients.
    _, nearest = ndimage.distance_transform_edt(~measured.reshape(shape3), return_indices=True)
    src = np.ravel_multi_index(tuple(nearest.reshape(3, -1)), shape3)
    return coef[src].reshape(*shape3, t, 2)


def evaluate_position_coefficients(coef: np.ndarray, index: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Gradients ``(N, 2)`` from coefficients ``(B, B, B, T, 2)`` at bins ``index (N, 3)`` and terms ``phi (N, T)``."""
    c = coef[index[:, 0], index[:, 1], index[:, 2]]  # (N, T, 2)
    return np.einsum("nt,ntk->nk", phi, c)
