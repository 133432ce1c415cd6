"""A check that needs no circle truth: fit a sphere to the reconstructed height map of a press.

A ball of radius ``R`` pressed into the gel leaves a spherical cap. Integrate a model's
normals to heights (the project's DST Poisson integrator: zero height at the image edge,
where the gel is flat) and fit a sphere to the top of the bump: if the normals are right, the
fitted radius is the ball's. Too flat normals (a model that under-tilts) give a larger
radius, too steep ones a smaller one; nothing about the contact circle is assumed.

Which pixels are fitted: the connected region around the highest point of the (lightly
smoothed) height map where the height is at least ``level`` of that peak. The rim is left
out on purpose: there the gel leaves the ball, the normals are steepest and a Poisson
solve spreads its error; the top of the cap carries the curvature.

The fit: algebraic (linear in the centre, ``z0`` and ``R^2 - |c|^2``) then geometric
(:func:`scipy.optimize.least_squares` on the distances to the sphere). The press depth is the
fitted sphere's apex height above the flat gel, ``z0 + R``.

**Round caps only.** A ball leaves a round cap whatever the scale of a model's tilts; a
reconstruction whose two principal curvatures (of its normals over the same pixels,
:func:`roundness`) differ by more than a factor two (:data:`MIN_ROUNDNESS`) has one tilt
direction that was not measured, and no single tilt gain makes it a ball: its "radius" is an
average of two wrong curvatures. Such a press gets no radius (``reason`` says so) and stays out
of the medians and of the ball-derived tilt gain (:mod:`calibration.ball_gain`). Measured with
the MLP on DIGIT presses it did not see (30 presses, 5 folds): 0.66-0.98, except three in the
DIGIT's lowest rows, where only the red and the blue light reach the gel, from opposite sides:
0.17, 0.35 and 0.56 (fitted radii 180, 70 and 60 % too large); the first two are left out.

**Contacts cut by the image edge.** The integrator holds the gel flat at the image edge; a
contact that reaches past it is cut there and its bump is no longer a sphere cap. Given the
press's contact circle (``contact``), a circle with less than :data:`MIN_RIM_INSIDE` of its rim
inside the image gets no radius either. Exact sphere-cap normals (balls of 16-113 px, contacts
of 0.6-0.9 of them) with 1.0 / 0.86 / 0.80 / 0.75 / 0.70 of the rim inside fit the ball 0.0 /
0.0-0.5 / 2-3 / 5-8 / 11-15 % too large; a press of a virtual sensor (seed 0) cut further fit
52 % too large from its exact normals.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage, optimize

__all__ = ["MIN_RIM_INSIDE", "MIN_ROUNDNESS", "fit_sphere", "cap_region", "ball_fit", "roundness"]

#: Smallest ratio of the reconstructed cap's principal curvatures (smaller over larger) for which
#: its fitted sphere measures the model's scale: one direction's tilts at less than half the
#: other's are no scale error a gain could mend (module docstring).
MIN_ROUNDNESS = 0.5

#: Smallest fraction of a contact's rim inside the image for which its integrated cap is the
#: ball's (exact normals: at most 0.5 % too large from 0.86 on; module docstring).
MIN_RIM_INSIDE = 0.85


def fit_sphere(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> dict[str, float]:
    """Least-squares sphere ``(x - x0)^2 + (y - y0)^2 + (z - z0)^2 = R^2`` through points.

    Parameters
    ----------
    x, y, z : ndarray, shape (N,)
        Points in mm (N >= 4, not coplanar).

    Returns
    -------
    dict
        ``x0``, ``y0``, ``z0``, ``radius`` (mm) and ``rms`` (RMS distance of the points to
        the sphere, mm).

    Examples
    --------
    >>> t = np.linspace(0.1, 1.2, 30); p = np.linspace(0, 6, 30)
    >>> T, P = np.meshgrid(t, p)
    >>> x = 2 * np.sin(T) * np.cos(P) + 0.3; y = 2 * np.sin(T) * np.sin(P); z = 2 * np.cos(T) - 1.5
    >>> s = fit_sphere(x.ravel(), y.ravel(), z.ravel())
    >>> round(s["radius"], 6), round(s["x0"], 6), round(s["z0"], 6)
    (2.0, 0.3, -1.5)
    """
    x, y, z = (np.asarray(a, np.float64).ravel() for a in (x, y, z))
    if len(x) < 4:
        raise ValueError(f"fit_sphere: needs at least 4 points, got {len(x)}")
    # Algebraic: |p|^2 = 2 c . p + k with k = R^2 - |c|^2 (linear in c and k).
    A = np.stack([2 * x, 2 * y, 2 * z, np.ones_like(x)], axis=1)
    sol = np.linalg.lstsq(A, x * x + y * y + z * z, rcond=None)[0]
    c = sol[:3]
    r = float(np.sqrt(max(sol[3] + c @ c, 1e-12)))
    pts = np.stack([x, y, z], axis=1)

    def resid(v):
        return np.linalg.norm(pts - v[:3], axis=1) - v[3]

    fit = optimize.least_squares(resid, np.r_[c, r], method="lm")
    x0, y0, z0, rad = (float(v) for v in fit.x)
    return {"x0": x0, "y0": y0, "z0": z0, "radius": abs(rad), "rms": float(np.sqrt(np.mean(fit.fun ** 2)))}


def cap_region(height: np.ndarray, level: float = 0.5, smooth_px: float = 1.0) -> np.ndarray:
    """Pixels ``(H, W)`` of the connected region around the peak where ``height >= level * peak``."""
    h = np.asarray(height, np.float64)
    hs = ndimage.gaussian_filter(h, smooth_px) if smooth_px > 0 else h
    peak = np.unravel_index(int(np.argmax(hs)), hs.shape)
    if not hs[peak] > 0:
        return np.zeros(h.shape, bool)
    lab, _ = ndimage.label(hs >= level * hs[peak])
    return lab == lab[peak]


def roundness(normals: np.ndarray, region: np.ndarray) -> float:
    """Smaller over larger principal curvature of the normals over a cap's pixels (1 for a sphere).

    The gradients ``(dh/dx, dh/dy)`` over ``region (H, W)`` are fitted as affine functions of the
    pixel position; the eigenvalues of the symmetric part of that Jacobian (sign: a bump's are
    positive) are the cap's two curvatures. Measured on the normals, not on integrated heights:
    the Poisson solve spreads a direction's missing tilt over both (x-tilts scaled by 0.4 gave a
    height map whose curvatures were 0.67 apart).

    Examples
    --------
    >>> from pipeline.base.frames import gradients_to_normals
    >>> rows, cols = np.mgrid[-5:6, -5:6] * 0.1   # a bump: dh/dx = -x, dh/dy = -y = +row
    >>> round(roundness(gradients_to_normals(-cols, rows), np.ones(cols.shape, bool)), 6)
    1.0
    >>> round(roundness(gradients_to_normals(-0.25 * cols, rows), np.ones(cols.shape, bool)), 6)
    0.25
    """
    from pipeline.base.frames import normals_to_gradients

    gx, gy = normals_to_gradients(np.asarray(normals, np.float64))
    rows, cols = np.nonzero(region)
    if len(rows) < 6:
        return 0.0
    # Pixel (row, col) -> (x, y) with y up, as the gradients are in the reconstruction frame.
    A = np.stack([np.ones(len(rows)), cols - cols.mean(), -(rows - rows.mean())], axis=1).astype(np.float64)
    jx = np.linalg.lstsq(A, gx[rows, cols], rcond=None)[0][1:]
    jy = np.linalg.lstsq(A, gy[rows, cols], rcond=None)[0][1:]
    J = -np.array([jx, jy])
    k = np.linalg.eigvalsh(0.5 * (J + J.T))  # curvatures (per pixel), ascending
    return float(max(k[0], 0.0) / k[1]) if k[1] > 0 else 0.0


def ball_fit(normals: np.ndarray, mm_per_px: float, ball_radius_mm: float, *, mask: np.ndarray | None = None,
             level: float = 0.5, true_depth_mm: float | None = None, min_pixels: int = 12,
             contact: tuple[float, float, float] | None = None) -> dict[str, Any]:
    """Integrate one press's normals (DST Poisson) and fit a sphere to the top of the bump.

    Parameters
    ----------
    normals : ndarray, shape (H, W, 3)
        Reconstruction-frame unit normals of one press (a model's prediction).
    mm_per_px, ball_radius_mm : float
    mask : ndarray, shape (H, W), bool, optional
        Valid normals; the integrator treats the others as flat gel.
    level : float
        Fraction of the peak height above which pixels are fitted (:func:`cap_region`).
    true_depth_mm : float, optional
        The press's depth, when known, for ``depth_error``.
    min_pixels : int
        Fewer fitted pixels than this: no fit (``radius_mm`` None, with a ``reason``).
    contact : (x, y, r), optional
        The press's contact circle (pixels; x the column): with less than
        :data:`MIN_RIM_INSIDE` of its rim inside the image, no fit (module docstring).

    Returns
    -------
    dict
        ``radius_mm``, ``depth_mm`` (apex height of the fitted sphere above the flat gel),
        ``radius_error`` (relative, signed), ``depth_error`` (relative, signed; None without
        ``true_depth_mm``), ``rms_mm``, ``pixels``, ``peak_height_mm``, ``roundness``
        (:func:`roundness`; below :data:`MIN_ROUNDNESS` the radius is None) and ``reason``.
    """
    from calibration.detect import rim_inside
    from pipeline.depth import poisson_dst

    normals = np.asarray(normals)
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise ValueError(f"ball_fit: normals must be (H, W, 3), got {normals.shape}")
    out: dict[str, Any] = {"radius_mm": None, "depth_mm": None, "radius_error": None, "depth_error": None,
                           "rms_mm": None, "pixels": 0, "peak_height_mm": None, "roundness": None, "reason": "ok"}
    if contact is not None and np.all(np.isfinite(contact)) and contact[2] > 0:
        inside = rim_inside(normals.shape[:2], contact[:2], contact[2])
        if inside < MIN_RIM_INSIDE:
            out["reason"] = (f"contact cut by the image border ({inside:.0%} of its rim inside, < "
                             f"{MIN_RIM_INSIDE:.0%}): the integration holds the gel flat at the edge, the cut cap is "
                             "no sphere")
            return out
    height = poisson_dst(np.asarray(normals, np.float64), mm_per_px, mask).height.astype(np.float64)
    region = cap_region(height, level)
    out.update(pixels=int(region.sum()), peak_height_mm=float(height.max()))
    if region.sum() < min_pixels:
        out["reason"] = f"no bump: {int(region.sum())} pixels above {level:.0%} of the peak (< {min_pixels})"
        return out
    rows, cols = np.nonzero(region)
    out["roundness"] = roundness(normals, region)
    if out["roundness"] < MIN_ROUNDNESS:
        out["reason"] = (f"not round: principal curvatures {out['roundness']:.2f} apart (< {MIN_ROUNDNESS:.2f}); one "
                         "tilt direction is not measured here")
        return out
    s = fit_sphere(cols * mm_per_px, rows * mm_per_px, height[rows, cols])
    depth = s["z0"] + s["radius"]
    out.update(radius_mm=s["radius"], depth_mm=float(depth), rms_mm=s["rms"],
               radius_error=float(s["radius"] / ball_radius_mm - 1.0))
    if true_depth_mm is not None and true_depth_mm > 0:
        out["depth_error"] = float(depth / true_depth_mm - 1.0)
    return out
