"""A no-contact reference built from the presses themselves, for captures without a clean frame.

Each press changes the gel only around its contact; elsewhere it shows the no-contact gel
(under its own drift). So the reference is the per-pixel median of the presses with each
press's contact masked out (:func:`build_reference`):

1. a first guess: the plain per-pixel median of every press (a contact is outvoted wherever
   fewer than half the presses touch that pixel);
2. each press's contact is found against it (:func:`calibration.detect.detect_press`) and
   masked (:func:`pipeline.normals.drift.contact_exclusion`: the contact, the gel bulge around it);
3. each press's drift against the guess is fitted outside its mask and removed
   (:func:`pipeline.normals.drift.fit_drift`), so every press speaks for the same lighting;
4. the reference is the median of the corrected presses over the unmasked ones, per pixel;
   pixels every press masks keep the first guess. Steps 2-4 run twice.

Presses spread over the gel are what makes this work: the report says how many presses each
pixel's median drew on (``min_presses_per_pixel``) and which pixels no press left uncovered.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["BUILT_REFERENCE_NOTE", "build_reference"]

#: What a capture with a built reference says about it (its ``reference_source`` attribute).
BUILT_REFERENCE_NOTE = ("built from the {k} presses (per-pixel median with each contact masked): no clean no-contact "
                        "frame")


def build_reference(frames: np.ndarray, ball_radius_px: float, *, iterations: int = 2, options=None,
                    exclude: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """The no-contact reference ``(P, H, W, C)`` (float32) of presses ``frames (K, P, H, W, C)``.

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        Linear values, at least three presses.
    ball_radius_px : float
    iterations : int
        Passes of detect - mask - drift - median after the plain median.
    options : DetectOptions, optional
    exclude : ndarray (H, W) bool, optional
        Pixels left out of the drift fits (markers).

    Returns
    -------
    reference : ndarray, float32, shape (P, H, W, C)
    report : dict
        ``presses``, ``iterations``, ``accepted`` (presses whose contact was found in the last
        pass), ``min_presses_per_pixel``, ``uncovered_fraction`` (pixels every press masked),
        ``note``.

    Examples
    --------
    >>> from calibration.synthetic import synthetic_sphere_capture
    >>> cap, tr = synthetic_sphere_capture((48, 64), 8, ball_radius_mm=1.2, num_leds=3, seed=2)
    >>> f, r = cap.linear()
    >>> built, rep = build_reference(f, 12.0)
    >>> float(np.abs(built - r).mean()) < 1.5, rep["accepted"]
    (True, 8)
    """
    from calibration.detect import detect_press
    from pipeline.normals.drift import contact_exclusion, fit_drift

    f = np.asarray(frames, np.float32)
    if f.ndim != 5 or len(f) < 3:
        raise ValueError(f"build_reference: needs presses (K >= 3, P, H, W, C), got {f.shape}")
    k, h, w = f.shape[0], f.shape[2], f.shape[3]
    guess = np.median(f, axis=0)
    ref = guess
    accepted = 0
    count = np.full((h, w), k)
    for _ in range(max(1, int(iterations))):
        stack = np.full(f.shape, np.nan, np.float32)
        count = np.zeros((h, w), int)
        accepted = 0
        for i in range(k):
            circ = detect_press(f[i], ref, ball_radius_px, options, exclude=exclude)
            accepted += int(circ.accepted)
            mask = contact_exclusion((h, w), circ.center_xy, circ.radius_px, ball_radius_px)
            ex = mask if exclude is None else mask | np.asarray(exclude, bool)
            drift = fit_drift(f[i], ref, ex)
            stack[i][:, ~mask, :] = drift.remove(f[i])[:, ~mask, :]
            count += ~mask
        with np.errstate(all="ignore"):
            med = np.nanmedian(stack, axis=0)
        ref = np.where(np.isfinite(med), med, guess).astype(np.float32)
    uncovered = float(np.mean(count == 0))
    note = BUILT_REFERENCE_NOTE.format(k=k)
    if uncovered > 0:
        note += f"; {uncovered:.1%} of the pixels were inside every press's contact and keep the plain median"
    return ref, {"presses": k, "iterations": int(iterations), "accepted": accepted,
                 "min_presses_per_pixel": int(count.min()), "uncovered_fraction": uncovered, "note": note}
