"""Calibrations shipped with a sensor profile: ``pipeline/capture/sensors/<profile>.calibration.h5``.

A profile with a shipped calibration works with no presses at all: ``iristac live --profile
digit`` and ``iristac reconstruct CAPTURE --profile digit`` without ``--calibration`` use it
(and say so). It is one unit's calibration, not yours: its error on another unit of the same
model was measured when it was built (``iristac bench calibration --shipped``: on an altered
copy of the unit's held-out presses, another resolution, turn and colour gain;
:mod:`calibration.altered_unit`) and is stored in the file's ``shipped`` attribute, which
:func:`shipped_note` prints. A calibration of your own unit does better (docs/calibration.md,
"Calibrate your own sensor").

Another unit's LEDs have other colours: before the shipped calibration sees them, its frames are
brought to the shipped unit's colours by one gain per channel, taken from the no-contact frames
alone (:func:`colour_gain`: the ratio of the per-channel medians of the shipped reference and of
the session's; :func:`colour_matched`, :class:`ColourMatchedCamera` for ``live``). On altered
copies of the DIGIT's held-out presses (five: one fixed, four drawn at random) it gave
4.73-4.79 deg and fitted balls 4.2-4.7 % off, against 4.64-5.53 deg and 2.4-9.0 % without it
(4.84 deg and 4.4 % on the unit itself; docs/calibration.md, "No presses at all").

The DIGIT's is built from the DIGIT frames of the Taxim project (MIT licence,
``sensors/LICENSE-digit-calibration.txt`` beside it): ``iristac bench calibration --shipped
--rebuild pipeline/capture/sensors/digit.calibration.h5`` rebuilds it.

Examples
--------
>>> shipped_calibration_path("digit").name
'digit.calibration.h5'
>>> shipped_calibration_path("gelsight-mini") is None
True
>>> info = shipped_info("digit")
>>> info["presses"], info["licence"]
(20, 'MIT')
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.camera import MappedCamera

__all__ = ["SHIPPED_SOLVER", "colour_matched_capture", "shipped_calibration_path", "shipped_info", "shipped_note", "shipped_reference", "colour_gain",
           "colour_matched", "ColourMatchedCamera", "SHIPPED_ATTR", "SUFFIX"]

#: The solver a shipped calibration is used with: the one model it holds.
SHIPPED_SOLVER = "mlp"

#: File name of a profile's shipped calibration: ``<profile name><SUFFIX>`` beside its YAML.
SUFFIX = ".calibration.h5"

#: The calibration.h5 attribute that describes a shipped calibration (where it comes from, its
#: licence, and its measured error on the unit it was built from and on another unit).
SHIPPED_ATTR = "shipped"


def shipped_calibration_path(profile) -> Path | None:
    """The calibration shipped with a built-in profile (a name or a SensorProfile), or None."""
    from pipeline.capture.sensor_profiles import PROFILES_DIR, SensorProfile, list_profiles

    name = profile.name if isinstance(profile, SensorProfile) else str(profile)
    if name not in list_profiles():
        return None
    if isinstance(profile, SensorProfile) and Path(profile.source).resolve() != (PROFILES_DIR / f"{name}.yaml").resolve():
        return None  # a profile file of the user's that shares a built-in's name: not that sensor
    path = PROFILES_DIR / f"{name}{SUFFIX}"
    return path if path.is_file() else None


def _shipped_path(profile_or_path) -> Path | None:
    """A shipped calibration's file: the path given (``.h5``), or the one a profile ships with."""
    if str(profile_or_path).endswith(".h5"):
        return Path(profile_or_path)
    return shipped_calibration_path(profile_or_path)


def shipped_info(profile_or_path) -> dict[str, Any]:
    """The ``shipped`` attribute of a shipped calibration (a profile name or the file's path);
    a :class:`UserError` when there is none."""
    from pipeline.base.errors import UserError
    from pipeline.base.store import read_record

    path = _shipped_path(profile_or_path)
    if path is None or not path.is_file():
        raise UserError(f"no calibration ships with sensor profile {profile_or_path!r}")
    info = read_record(path, load=False).meta.get(SHIPPED_ATTR)
    if not info:
        raise UserError(f"{path}: not a shipped calibration (no {SHIPPED_ATTR!r} attribute)")
    return dict(info)


def shipped_reference(path) -> np.ndarray:
    """The shipped calibration's no-contact reference ``(P, H, W, C)`` float32 (its MLP's)."""
    from pipeline.base.store import read_record

    return np.asarray(read_record(path).data["models/mlp/reference"], np.float32)


def colour_gain(reference, shipped_ref) -> np.ndarray:
    """One gain per channel ``(C,)`` that brings a session's no-contact frame ``(..., H, W, C)``
    to the shipped unit's colours: the ratio of their per-channel medians.

    >>> ref = np.full((4, 4, 3), [100.0, 50.0, 80.0])
    >>> colour_gain(ref * [1.1, 0.9, 1.0], ref).round(3).tolist()
    [0.909, 1.111, 1.0]
    """
    ref = np.asarray(reference, np.float64)
    c = ref.shape[-1]
    session = np.median(ref.reshape(-1, c), axis=0)
    return (np.median(np.asarray(shipped_ref, np.float64).reshape(-1, c), axis=0) / np.maximum(session, 1e-6))


def colour_matched(frames, gain) -> np.ndarray:
    """Frames ``(..., C)`` times ``gain (C,)``, rounded and clipped to their integer dtype (kept
    as float for float frames)."""
    f = np.asarray(frames)
    out = f.astype(np.float32) * np.asarray(gain, np.float32)
    if np.issubdtype(f.dtype, np.integer):
        out = np.clip(np.rint(out), 0, np.iinfo(f.dtype).max).astype(f.dtype)
    return out


def colour_matched_capture(capture, calibration):
    """``(capture, gain)``: an in-memory capture with its frames and reference brought to a shipped
    calibration's colours (:func:`colour_gain` from its no-contact frame, :func:`colour_matched`)."""
    from dataclasses import replace

    gain = colour_gain(capture.reference, shipped_reference(calibration))
    return replace(capture, frames=colour_matched(capture.frames, gain),
                   reference=colour_matched(capture.reference, gain)), gain


class ColourMatchedCamera(MappedCamera):
    """A camera whose frames are brought to a shipped calibration's colours: the gain is taken
    from its first frame (the no-contact frame ``live --reference start`` takes) against
    ``shipped_ref`` and applied to that frame and every later one. ``gain`` is None before."""

    def __init__(self, camera, shipped_ref, say=None):
        super().__init__(camera)
        self.shipped_ref, self.gain, self.say = shipped_ref, None, say

    def map_image(self, image: np.ndarray) -> np.ndarray:
        if self.gain is None:
            self.gain = colour_gain(image, self.shipped_ref)
            if self.say is not None:
                self.say("colours matched to the shipped calibration's from the first frame (gain per channel "
                         + " / ".join(f"{g:.3f}" for g in self.gain) + ")")
        return colour_matched(image, self.gain)


def shipped_note(profile_or_path) -> str:
    """The line ``live`` and ``reconstruct`` print when they use a shipped calibration: what it
    is built from, its licence and the error measured on another unit.

    >>> print(shipped_note("digit"))    # doctest: +ELLIPSIS
    shipped DIGIT calibration (.../digit.calibration.h5; built from 20 presses of one unit, MIT licence, ...): on another unit expect about ... deg mean normal error (measured on an altered copy of its 10 held-out presses, colours matched from the no-contact frame: ...; ... deg on the unit itself); calibrate your own unit for better (docs/calibration.md)
    """
    info = shipped_info(profile_or_path)
    path = _shipped_path(profile_or_path)
    orig, alt = info["original"], info["altered"]
    return (f"shipped {info['sensor']} calibration ({path}; built from {info['presses']} presses of one unit, "
            f"{info['licence']} licence, {info['attribution']}): on another unit expect about "
            f"{alt['mean_deg']:.1f} deg mean normal error (measured on an altered copy of its {orig['presses']} "
            f"held-out presses, colours matched from the no-contact frame: {alt['alteration']}; "
            f"{orig['mean_deg']:.1f} deg on the unit itself); "
            "calibrate your own unit for better (docs/calibration.md)")
