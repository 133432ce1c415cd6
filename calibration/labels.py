"""Hand-labelled contact circles: as circles to calibrate on or to judge against, and compared with detected ones.

A capture may carry hand labels ``labels/center_xy (K, 2)`` (x = column, y = row, pixels) and
``labels/radius_px (K,)`` (``iristac import images --labels``, the GelSight npz's
``touch_center_xy`` / ``touch_radius_px``, the labeller ``iristac label``), NaN where a press
has none, and ``labels/rejected (K,)``: presses a person rejected (rejected circles here).
Labels are drawn by eye, often on a coarse grid, and a labelled radius may exceed the ball's
(a contact disc cannot: the shared real frames have 17 px labels on a 16.1 px ball), so the
contact radius used for the truth is clamped to ``clamp_fraction`` of the ball radius, as the
detector clamps its own.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from calibration.detect import Circle
from pipeline.base.errors import UserError

__all__ = ["label_circles", "capture_label_circles", "has_labels", "label_errors", "LABEL_CLAMP_FRACTION"]

#: Contact radius of a labelled circle at most this fraction of the ball radius (as the detector's default).
LABEL_CLAMP_FRACTION = 0.95


def has_labels(capture) -> bool:
    """Whether a :class:`pipeline.base.capture.Capture` carries hand labels (centre and radius)."""
    lab = getattr(capture, "labels", None) or {}
    return "center_xy" in lab and "radius_px" in lab


def label_circles(center_xy: np.ndarray, radius_px: np.ndarray, ball_radius_px: float,
                  clamp_fraction: float = LABEL_CLAMP_FRACTION) -> list[Circle]:
    """Hand-labelled circles as accepted :class:`Circle` records (contact radius clamped below the ball).

    Parameters
    ----------
    center_xy : ndarray, shape (K, 2)
        Labelled centres (x = column, y = row) in pixels.
    radius_px : ndarray, shape (K,)
        Labelled radii in pixels (kept as ``radius_px``).
    ball_radius_px : float
        The ball's radius in pixels.
    clamp_fraction : float
        ``contact_radius_px = min(radius_px, clamp_fraction * ball_radius_px)``.

    Returns
    -------
    list of Circle, length K
        A label that is not finite or not positive is a rejected circle saying so.

    Examples
    --------
    >>> c = label_circles(np.array([[40.0, 30.0]]), np.array([17.0]), 16.0)
    >>> c[0].center_xy, c[0].radius_px, round(c[0].contact_radius_px, 2), c[0].accepted
    ((40.0, 30.0), 17.0, 15.2, True)
    """
    limit = clamp_fraction * float(ball_radius_px)
    out = []
    for (x, y), r in zip(np.asarray(center_xy, float).reshape(-1, 2), np.asarray(radius_px, float).ravel()):
        ok = bool(np.isfinite([x, y, r]).all() and r > 0)
        reason = "hand label" if ok else f"hand label not usable (x {x}, y {y}, radius {r})"
        if ok and r > limit:
            reason += f"; contact radius clamped from {r:.2f} to {limit:.2f} px ({clamp_fraction} x ball radius)"
        out.append(Circle((float(x), float(y)), float(r), float(min(r, limit)) if ok else 0.0, 1.0 if ok else 0.0,
                          ok, reason))
    return out


def capture_label_circles(capture, ball_radius_px: float, source: str = "capture",
                          clamp_fraction: float = LABEL_CLAMP_FRACTION) -> list[Circle]:
    """The hand-labelled circles of a capture (:func:`label_circles`); :class:`UserError` when it has none.

    Examples
    --------
    >>> from pipeline.base.capture import Capture
    >>> cap = Capture(frames=np.zeros((1, 1, 8, 8, 3), np.uint8), reference=np.zeros((1, 8, 8, 3), np.uint8),
    ...               drive=np.eye(3, dtype=np.float32)[None], brightness=np.ones(1, np.float32), mm_per_px=0.1)
    >>> capture_label_circles(cap, 16.0, "cap.h5")
    Traceback (most recent call last):
    ...
    pipeline.base.errors.UserError: cap.h5: no hand labels (labels/center_xy, labels/radius_px) to calibrate on; import them with iristac import images --labels LABELS.csv, or use --circles detected
    """
    if not has_labels(capture):
        raise UserError(f"{source}: no hand labels (labels/center_xy, labels/radius_px) to calibrate on; import them "
                        "with iristac import images --labels LABELS.csv, or use --circles detected")
    k = int(np.asarray(capture.frames).shape[0])
    c, r = np.asarray(capture.labels["center_xy"], float), np.asarray(capture.labels["radius_px"], float)
    if c.shape != (k, 2) or r.shape != (k,):
        raise UserError(f"{source}: labels/center_xy {c.shape} and labels/radius_px {r.shape} do not match {k} "
                        f"presses (expected ({k}, 2) and ({k},))")
    circles = label_circles(c, r, ball_radius_px, clamp_fraction)
    rejected = capture.labels.get("rejected")
    if rejected is not None:
        for i in np.flatnonzero(np.asarray(rejected, bool).reshape(-1)[:k]):
            circles[i].accepted = False
            circles[i].reason = "rejected by hand (labels/rejected)"
    return circles


def label_errors(circles: Sequence[Circle], center_xy: np.ndarray, radius_px: np.ndarray) -> dict[str, Any]:
    """Median centre and radius error (px) of the accepted circles against hand labels.

    Also the median signed centre offset ``center_offset_px_median = [dx, dy]`` (circle minus
    label): a bias shared by all presses shows there, not in the error's size alone.
    """
    acc = np.array([c.accepted for c in circles])
    c = np.array([c.center_xy for c in circles]).reshape(-1, 2)
    r = np.array([c.radius_px for c in circles])
    ce = np.hypot(*(c - np.asarray(center_xy, float)).T)[acc]
    re = np.abs(r - np.asarray(radius_px, float))[acc]
    return {"center_error_px_median": float(np.median(ce)) if ce.size else None,
            "radius_error_px_median": float(np.median(re)) if re.size else None,
            "center_offset_px_median": np.median((c - np.asarray(center_xy, float))[acc], axis=0).tolist()
            if ce.size else None,
            "center_error_px": ce.tolist(), "radius_error_px": re.tolist()}
