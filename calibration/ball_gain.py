"""The tilt scale that makes a model's reconstructions the ball's size, from presses it did not see.

Every model predicts tilts a little too small or too large on presses it never saw: noise
pulls them toward flat, a blurred rim pushes the middle of the cap steeper (regression toward
the typical tilt). Reconstructed, a press then comes out as a sphere of the wrong radius. The
ball's radius is known, so it calibrates that scale: during cross-validation each fold's model
reconstructs some of its held-out presses (:class:`OutOfFoldBalls`, a
:func:`calibration.validate.cross_validate` fold hook), a sphere is fitted to each
(:func:`calibration.ballfit.ball_fit`), and the gain is the one that makes the median fitted
radius the ball's (:meth:`OutOfFoldBalls.gain`: for small tilts the fitted radius is inversely
proportional to the tilt scale, so the first guess is the median radius over the ball's; one
fixed-point step through the tilt clip refines it).

No circle truth enters (the fit needs only normals), no press shapes the model that
reconstructs it, and the test presses of ``iristac eval calibration`` stay an independent
check. The uncorrected figure (``raw_radius_error``) is what the quality gate judges
(:mod:`calibration.gate`): far off means the model and the ball disagree.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["BALL_GAIN_PRESSES", "BALL_GAIN_RANGE", "MIN_BALL_FITS", "OutOfFoldBalls"]

#: Held-out presses reconstructed per calibration (spread over the folds). The per-press fitted
#: radius scatters by about 6 % (DIGIT), so the gain carries a few per cent of noise either way:
#: with 20 presses the DIGIT test presses' ball fit went from 10.4 to 7.3 % and the shared
#: GelSight frames' from 2.3-2.7 to 2.8-3.8 % (three MLP seeds; the fixed-split bound there is 3 %).
BALL_GAIN_PRESSES = 10
#: A ball-derived gain outside this range is not applied (the models and the ball disagree too
#: much for a scale to mend; the quality gate says so).
BALL_GAIN_RANGE = (0.67, 1.5)
#: Fewest successful sphere fits for a ball-derived gain.
MIN_BALL_FITS = 3


class OutOfFoldBalls:
    """Fold hook: each fold's model reconstructs up to a share of its held-out presses.

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        Linear, drift-free frames of the calibration's presses.
    reference : ndarray, shape (P, H, W, C)
    accepted : sequence of int
        Presses that may be reconstructed (accepted ones).
    mm_per_px, ball_radius_mm : float
    folds : int
    markers : ndarray (H, W) bool, optional
    max_presses : int
    contacts : sequence of (x, y, r), optional
        Each press's contact circle (pixels), so that a press cut by the image border is not
        fitted (:func:`calibration.ballfit.ball_fit`'s ``contact``).
    """

    def __init__(self, frames, reference, accepted, mm_per_px: float, ball_radius_mm: float, folds: int,
                 markers=None, max_presses: int = BALL_GAIN_PRESSES, contacts=None):
        self.frames, self.reference, self.markers = frames, reference, markers
        self.contacts = None if contacts is None else [tuple(map(float, c)) for c in contacts]
        self.accepted = {int(k) for k in accepted}
        self.mm, self.ball = float(mm_per_px), float(ball_radius_mm)
        self.per_fold = max(1, int(np.ceil(max_presses / max(1, folds))))
        # (press, normals (H, W, 3), usable (H, W), contact circle or None)
        self.maps: list[tuple[int, np.ndarray, np.ndarray, tuple[float, ...] | None]] = []

    def __call__(self, model, held_out: list[int]) -> None:
        chosen = [p for p in held_out if p in self.accepted]
        chosen = [chosen[i] for i in np.unique(np.linspace(0, len(chosen) - 1, min(self.per_fold, len(chosen)))
                                               .round().astype(int))] if chosen else []
        if not chosen:
            return
        maps = model.normal_maps(self.frames[chosen], self.reference, markers=self.markers)
        for i, k in enumerate(chosen):
            usable = maps.mask[i] if maps.filled is None else maps.mask[i] | maps.filled
            self.maps.append((k, np.asarray(maps.normals[i], np.float64), usable,
                              None if self.contacts is None else self.contacts[k]))

    def radii(self, gain: float = 1.0, max_tilt: float | None = None) -> list[float]:
        """Fitted sphere radii (mm) of the reconstructed presses with their tilts scaled by ``gain``."""
        from calibration.ballfit import ball_fit
        from calibration.models.base import scale_tilt

        out = []
        for _, n, usable, contact in self.maps:
            scaled = n if gain == 1.0 and max_tilt is None else scale_tilt(n, gain, max_tilt)[0]
            r = ball_fit(scaled, self.mm, self.ball, mask=usable, contact=contact)
            if r["radius_mm"] is not None:
                out.append(float(r["radius_mm"]))
        return out

    def gain(self, max_tilt: float | None = None) -> dict[str, Any]:
        """The tilt gain that makes the median fitted radius the ball's, with the figures behind it.

        Returns ``{"gain": float or None, "raw_radius_error", "radius_error", "presses", "attempted",
        "note"}`` (``presses``: reconstructions that gave a round cap's sphere, of ``attempted``):
        ``raw_radius_error`` the median fitted radius over the ball's, minus 1, before any gain;
        ``radius_error`` the same at the first guess of the gain (the last step removes most of
        it); ``gain`` None when fewer than :data:`MIN_BALL_FITS` presses reconstruct as a round cap or the
        gain falls outside :data:`BALL_GAIN_RANGE` (then ``note`` says why).
        """
        raw = self.radii()
        out: dict[str, Any] = {"gain": None, "presses": len(raw), "attempted": len(self.maps), "raw_radius_error": None,
                               "radius_error": None, "note": ""}
        if len(raw) < MIN_BALL_FITS:
            out["note"] = (f"only {len(raw)} of {len(self.maps)} held-out presses reconstruct as a round cap "
                           f"(< {MIN_BALL_FITS}; calibration.ballfit.MIN_ROUNDNESS)")
            return out
        out["raw_radius_error"] = float(np.median(raw) / self.ball - 1.0)
        g = float(np.median(raw)) / self.ball
        if BALL_GAIN_RANGE[0] <= g <= BALL_GAIN_RANGE[1]:
            # One fixed-point step through the clip; what is left after it is reported.
            step = float(np.median(self.radii(g, max_tilt))) / self.ball
            out["radius_error"] = step - 1.0
            g *= step
        if not BALL_GAIN_RANGE[0] <= g <= BALL_GAIN_RANGE[1]:
            out["note"] = (f"a tilt gain of {g:.2f} would be needed to make the reconstructions the ball's size "
                           f"(outside {BALL_GAIN_RANGE[0]}-{BALL_GAIN_RANGE[1]}): not applied")
            out["radius_error"] = None
            return out
        out["gain"] = g
        return out
