"""Photometric refinement of the contact centres: the centre that the shading itself points to.

The edge detector (:mod:`calibration.detect`) finds where the difference image falls off,
which on a real gel is blurred and lit unevenly (the rim facing a bright LED stays bright
further out), so its centres scatter by about a pixel. The shading inside the contact holds
a sharper cue: on a sphere of radius ``R`` the outward normal at reconstruction-frame point
``x`` is ``n = (x - x0, y - y0, z) / R``, so every contact pixel whose normal has been
measured votes for a centre ``x0 = x - R n_x``, ``y0 = y - R n_y``.

Normals are measured with a light model fitted on the *other* presses (cross-fitting: the
press being refined never shapes the model that measures it), the centre is the median of
the votes (robust to pixels in shadow or near the rim), and the samples are gathered again
around the new centres for the next iteration. The radius is left to the detector. A press
whose centre would move further than ``max_shift_px`` keeps the detector's centre, with the
reason noted.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Callable

import numpy as np

from calibration.detect import Circle
from calibration.models.base import CalibrationModel
from calibration.models.nearfield import NearFieldModel
from calibration.samples import collect_samples
from calibration.validate import fold_assignment
from pipeline.base.frames import pixel_to_recon

__all__ = ["recon_to_pixel_offsets", "centre_votes", "refine_centres"]


def recon_to_pixel_offsets(dx: np.ndarray, dy: np.ndarray, shape: tuple[int, int], mm_per_px: float
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets ``(d_row, d_col)`` of reconstruction-frame offsets ``(dx, dy)`` in mm.

    Inverts the (affine) :func:`pipeline.base.frames.pixel_to_recon`, so the axis signs come from
    :mod:`pipeline.base.frames` and nowhere else.

    Examples
    --------
    >>> dr, dc = recon_to_pixel_offsets(np.array([0.5]), np.array([0.5]), (3, 3), 0.5)
    >>> dr.tolist(), dc.tolist()
    ([-1.0], [1.0])
    """
    x0, y0 = pixel_to_recon(0.0, 0.0, shape, mm_per_px)
    xr, yr = pixel_to_recon(1.0, 0.0, shape, mm_per_px)  # one row down
    xc, yc = pixel_to_recon(0.0, 1.0, shape, mm_per_px)  # one column right
    J = np.array([[xr - x0, xc - x0], [yr - y0, yc - y0]], dtype=np.float64)  # recon mm per (row, col)
    inv = np.linalg.inv(J)
    d = np.stack([np.asarray(dx, np.float64), np.asarray(dy, np.float64)])
    d_rc = np.tensordot(inv, d, axes=1)
    return d_rc[0] + 0.0, d_rc[1] + 0.0


def centre_votes(rows: np.ndarray, cols: np.ndarray, normals: np.ndarray, ball_radius_mm: float,
                 shape: tuple[int, int], mm_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre ``(row0, col0)`` each contact pixel's measured normal points to, on a sphere.

    Parameters
    ----------
    rows, cols : ndarray, shape (N,)
        Contact pixels.
    normals : ndarray, shape (N, 3)
        Their measured unit normals (reconstruction frame).
    ball_radius_mm, mm_per_px : float
    shape : (H, W)

    Returns
    -------
    row0, col0 : ndarray, shape (N,)

    Examples
    --------
    The exact sphere-cap normals vote for the exact centre:

    >>> from calibration.truth import sphere_cap
    >>> cap = sphere_cap((30, 30), (14.3, 16.6), 8.0, 1.0, 0.1)
    >>> r, c = np.nonzero(cap.contact)
    >>> r0, c0 = centre_votes(r, c, cap.normals[r, c], 1.0, (30, 30), 0.1)
    >>> round(float(np.median(r0)), 6), round(float(np.median(c0)), 6)
    (14.3, 16.6)
    """
    normals = np.asarray(normals, dtype=np.float64)
    if normals.ndim != 2 or normals.shape[1] != 3 or len(normals) != len(rows):
        raise ValueError(f"centre_votes: normals must be (N, 3) with N = {len(rows)}, got {normals.shape}")
    d_row, d_col = recon_to_pixel_offsets(ball_radius_mm * normals[:, 0], ball_radius_mm * normals[:, 1], shape,
                                          mm_per_px)
    return np.asarray(rows, np.float64) - d_row, np.asarray(cols, np.float64) - d_col


def refine_centres(frames: np.ndarray, reference: np.ndarray, circles: list[Circle], ball_radius_mm: float,
                   mm_per_px: float, *, iterations: int = 2, folds: int = 5, seed: int = 0, shrink_px: float = 2.0,
                   saturation: float | None = None, max_shift_px: float = 4.0,
                   make_model: Callable[[], CalibrationModel] = NearFieldModel, exclude: np.ndarray | None = None
                   ) -> tuple[list[Circle], dict[str, Any]]:
    """Move each accepted circle's centre to where its measured normals point (see module doc).

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        Linear frames.
    reference : ndarray, shape (P, H, W, C)
    circles : list of Circle, length K
        Detected circles; rejected ones are passed through unchanged.
    ball_radius_mm, mm_per_px : float
    iterations : int
        Refinement passes (each: gather samples, cross-fit, vote); 0 returns the input.
    folds : int
        Press groups of the cross-fitting.
    shrink_px, saturation
        As in :func:`calibration.samples.collect_samples`.
    max_shift_px : float
        Largest total move from the detected centre; beyond it the detector's centre is kept.
    make_model : callable
        Returns a fresh light model used to measure normals (default: near-field, degree 2).
    exclude : ndarray, shape (H, W), bool, optional
        Pixels never sampled (gel markers).

    Returns
    -------
    circles : list of Circle
        Accepted circles with refined ``center_xy`` and ``shift_xy`` (the total move in px).
    report : dict
        ``iterations``, ``median_move_px`` (per iteration), ``kept_detected`` (press indices).
    """
    from pipeline.base.threads import limit_threads

    with limit_threads(blas=1):  # why: see calibration.calibrate.calibrate
        return _refine(frames, reference, circles, ball_radius_mm, mm_per_px, iterations, folds, seed, shrink_px,
                       saturation, max_shift_px, make_model, exclude)


def _refine(frames, reference, circles, ball_radius_mm, mm_per_px, iterations, folds, seed, shrink_px, saturation,
            max_shift_px, make_model, exclude=None):
    out = list(circles)
    accepted = [k for k, c in enumerate(out) if c.accepted]
    report: dict[str, Any] = {"iterations": int(iterations), "median_move_px": [], "kept_detected": []}
    if iterations <= 0 or len(accepted) < 2:
        return out, report
    shape = tuple(np.asarray(reference).shape[1:3])
    assign = fold_assignment(np.array(accepted), folds, seed)
    kept: set[int] = set()
    for _ in range(int(iterations)):
        samples = collect_samples(frames, reference, out, ball_radius_mm, mm_per_px, shrink_px=shrink_px,
                                  saturation=saturation, exclude=exclude)
        moves = []
        new = list(out)
        for f in sorted(set(assign.values())):
            test = [k for k, g in assign.items() if g == f]
            model = make_model()
            model.fit(samples.subset(~np.isin(samples.press, test)), reference)
            for k in test:
                s = samples.subset((samples.press == k) & samples.contact)
                if len(s) < 10 or k in kept:
                    continue
                n, ok = model.predict(s)
                if ok.sum() < 10:
                    continue
                r0, c0 = centre_votes(s.rows[ok], s.cols[ok], n[ok], ball_radius_mm, shape, mm_per_px)
                cx, cy = float(np.median(c0)), float(np.median(r0))
                c = out[k]
                sx, sy = c.shift_xy
                det_x, det_y = c.center_xy[0] - sx, c.center_xy[1] - sy
                if np.hypot(cx - det_x, cy - det_y) > max_shift_px:
                    kept.add(k)
                    new[k] = replace(c, center_xy=(det_x, det_y), shift_xy=(0.0, 0.0),
                                     reason=c.reason + f"; photometric centre {np.hypot(cx - det_x, cy - det_y):.1f} "
                                                       f"px away (> {max_shift_px}), detected centre kept")
                    continue
                moves.append(float(np.hypot(cx - c.center_xy[0], cy - c.center_xy[1])))
                new[k] = replace(c, center_xy=(cx, cy), shift_xy=(cx - det_x, cy - det_y))
        out = new
        report["median_move_px"].append(float(np.median(moves)) if moves else 0.0)
    report["kept_detected"] = sorted(kept)
    return out, report
