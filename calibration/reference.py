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

**Even with a clean frame** the built reference can be the better one: the no-contact frame is
one noisy frame taken at another moment, the median of many presses has less noise (with noise
alone, presses are left with about 0.75-0.8 of the residual against one frame) and is taken
under their own light. :func:`compare_with_built` measures which one presses match, on presses the built
reference did not see (built from every other press, judged on the rest: the drift left after
removing each press's own gain and offset, away from its contact). Measured (built from the
even presses, judged on the odd ones, RMS DN, median): DIGIT ``frame_30.jpg`` 4.57, built 3.57
(the blue of the frame 7.5 % brighter than the presses', its red hot spot's edge moved); shared
GelSight background 6.64, built 4.34; the same frames drifted 6.79, 4.74. Calibrated on presses
0-19 and tested on 20-29 (MLP, test error / ball radius): DIGIT 4.98 deg / 7.4 % with the frame,
4.82 deg / 4.9 % built; GelSight 4.64 / 2.3 % and 4.25 / 2.4 %; drifted 4.62 / 3.3 % and
4.30 / 2.9 %. So ``iristac import images`` prefers the built reference when the presses match it
better by :data:`PREFER_BUILT_RATIO` (and there are :data:`MIN_PRESSES_TO_COMPARE` presses to
build from and judge on), and says so; naming the frame (``--reference NAME``) keeps it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["BUILT_REFERENCE_NOTE", "MIN_PRESSES_TO_COMPARE", "NO_CLEAN_FRAME", "PREFER_BUILT_RATIO", "build_reference",
           "compare_with_built", "nanmedian_first_axis"]

#: What a capture with a built reference says about it (its ``reference_source`` attribute); ``why``
#: defaults to :data:`NO_CLEAN_FRAME`.
BUILT_REFERENCE_NOTE = "built from the {k} presses (per-pixel median with each contact masked){why}"

#: Why a reference was built when no frame is free of contact.
NO_CLEAN_FRAME = ": no clean no-contact frame"


#: A found no-contact frame gives way to a reference built from the presses when presses the built one
#: did not see are left with at most this fraction of the frame's drift residual (measured ratios: DIGIT
#: 0.78, shared GelSight 0.65, the same drifted 0.70; module docstring). A margin, not 1: the median must
#: be clearly better than the one frame a user took on purpose. Noise alone gives 0.75-0.8 (a median of
#: 5-15 presses against one frame as noisy as a press), so a frame as noisy as the presses gives way; a
#: frame averaged over many exposures under the presses' light is kept.
PREFER_BUILT_RATIO = 0.9

#: Fewest presses for :func:`compare_with_built` (half build, half judge): a median of fewer than five
#: presses leaves contacts and noise in, and a handful of judged presses is no measurement.
MIN_PRESSES_TO_COMPARE = 10


def nanmedian_first_axis(stack: np.ndarray) -> np.ndarray:
    """``np.nanmedian(stack, axis=0)`` (NaN where a column is all NaN, without a warning), by one sort.

    numpy's nanmedian over a short first axis goes through masked arrays: 3.8 s for 30 presses of
    640 x 480 x 3, against 0.5 s sorted here (NaN sorts last; the middle one or two of each
    column's valid values are averaged), equal to the last bit.

    Examples
    --------
    >>> nanmedian_first_axis(np.array([[1.0, np.nan, np.nan], [3.0, 2.0, np.nan], [2.0, 4.0, np.nan]])).tolist()
    [2.0, 3.0, nan]
    """
    x = np.asarray(stack)
    if x.ndim < 1 or x.shape[0] == 0:
        raise ValueError(f"nanmedian_first_axis: needs at least one entry along the first axis, got {x.shape}")
    ordered = np.sort(x, axis=0)
    n = np.sum(~np.isnan(x), axis=0)
    lo = np.maximum((n - 1) // 2, 0)[None]
    hi = (n // 2)[None]
    mid = 0.5 * (np.take_along_axis(ordered, lo, 0)[0] + np.take_along_axis(ordered, hi, 0)[0])
    return np.where(n > 0, mid, np.nan).astype(x.dtype, copy=False)


def build_reference(frames: np.ndarray, ball_radius_px: float, *, iterations: int = 2, options=None,
                    exclude: np.ndarray | None = None, why: str = NO_CLEAN_FRAME) -> tuple[np.ndarray, dict[str, Any]]:
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
    why : str
        Why it was built, appended to the note (:data:`BUILT_REFERENCE_NOTE`).

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
        med = nanmedian_first_axis(stack)
        ref = np.where(np.isfinite(med), med, guess).astype(np.float32)
    uncovered = float(np.mean(count == 0))
    note = BUILT_REFERENCE_NOTE.format(k=k, why=why)
    if uncovered > 0:
        note += f"; {uncovered:.1%} of the pixels were inside every press's contact and keep the plain median"
    return ref, {"presses": k, "iterations": int(iterations), "accepted": accepted,
                 "min_presses_per_pixel": int(count.min()), "uncovered_fraction": uncovered, "note": note}


def compare_with_built(frames: np.ndarray, frame_reference: np.ndarray, ball_radius_px: float, *, options=None,
                       exclude: np.ndarray | None = None) -> dict[str, Any]:
    """Which reference presses match better: a no-contact frame, or one built from other presses.

    The reference is built (:func:`build_reference`) from the even presses; each odd press's
    contact is found against the frame and masked (:func:`pipeline.normals.drift.contact_exclusion`)
    and its drift fitted against each reference (:func:`pipeline.normals.drift.fit_drift`,
    gain and offset per channel): what is left (RMS over the fitted pixels) is how far the press's
    lighting differs from that reference's beyond a brightness change.

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        Linear presses, K >= :data:`MIN_PRESSES_TO_COMPARE`.
    frame_reference : ndarray, shape (P, H, W, C)
        The no-contact frame.
    ball_radius_px : float
    options : DetectOptions, optional
    exclude : ndarray (H, W) bool, optional
        Pixels left out everywhere (markers).

    Returns
    -------
    dict
        ``frame_residual_dn``, ``built_residual_dn`` (medians over the judged presses), ``ratio``
        (built over frame), ``presses_built``, ``presses_judged`` and ``prefer_built`` (``ratio``
        below :data:`PREFER_BUILT_RATIO`).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> gel = rng.uniform(80, 160, (1, 40, 60, 3)).astype(np.float32)
    >>> presses = gel + rng.normal(0, 2, (12, 1, 40, 60, 3)).astype(np.float32)
    >>> for k in range(12):
    ...     presses[k, :, 10:20, 4 * k:4 * k + 10] += 60          # a contact, somewhere else each time
    >>> stale = gel * np.linspace(0.9, 1.1, 60)[None, None, :, None]  # the light moved since
    >>> r = compare_with_built(presses, stale.astype(np.float32), 5.0)
    >>> r["prefer_built"], r["presses_built"], r["presses_judged"]
    (True, 6, 6)
    """
    from calibration.detect import detect_press
    from pipeline.normals.drift import contact_exclusion, fit_drift

    f = np.asarray(frames, np.float32)
    ref = np.asarray(frame_reference, np.float32)
    if f.ndim != 5 or len(f) < MIN_PRESSES_TO_COMPARE:
        raise ValueError(f"compare_with_built: needs presses (K >= {MIN_PRESSES_TO_COMPARE}, P, H, W, C), "
                         f"got {f.shape}")
    if ref.shape != f.shape[1:]:
        raise ValueError(f"compare_with_built: frame_reference must be {f.shape[1:]} like one press, got {ref.shape}")
    built, _ = build_reference(f[0::2], ball_radius_px, options=options, exclude=exclude)
    hw = f.shape[2:4]
    frame_res, built_res = [], []
    for press in f[1::2]:
        circ = detect_press(press, ref, ball_radius_px, options, exclude=exclude)
        mask = contact_exclusion(hw, circ.center_xy, circ.radius_px, ball_radius_px)
        ex = mask if exclude is None else mask | np.asarray(exclude, bool)
        frame_res.append(fit_drift(press, ref, ex).residual_dn)
        built_res.append(fit_drift(press, built, ex).residual_dn)
    fr, br = float(np.median(frame_res)), float(np.median(built_res))
    ratio = br / fr if fr > 0 else 1.0
    return {"frame_residual_dn": fr, "built_residual_dn": br, "ratio": ratio, "presses_built": len(f[0::2]),
            "presses_judged": len(f[1::2]), "prefer_built": bool(ratio < PREFER_BUILT_RATIO)}
