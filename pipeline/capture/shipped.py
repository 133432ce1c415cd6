"""Calibrations shipped with a sensor profile: ``pipeline/capture/sensors/<profile>.calibration.h5``.

A profile with a shipped calibration works with no presses at all: ``iristac live --profile
digit`` and ``iristac reconstruct CAPTURE --profile digit`` without ``--calibration`` use it
(and say so). It is one unit's calibration, not yours: its error on another unit of the same
model was measured when it was built (``iristac bench calibration --shipped``: on an altered
copy of the unit's held-out presses, another resolution, turn and colour gain;
:mod:`calibration.altered_unit`) and is stored in the file's ``shipped`` attribute, which
:func:`shipped_note` prints. A calibration of your own unit does better (docs/calibration.md,
"Calibrate your own sensor").

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

__all__ = ["shipped_calibration_path", "shipped_info", "shipped_note", "SHIPPED_ATTR", "SUFFIX"]

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


def shipped_info(profile_or_path) -> dict[str, Any]:
    """The ``shipped`` attribute of a shipped calibration (a profile name or the file's path);
    a :class:`UserError` when there is none."""
    from pipeline.base.errors import UserError
    from pipeline.base.store import read_record

    path = Path(profile_or_path) if str(profile_or_path).endswith(".h5") else \
        shipped_calibration_path(profile_or_path)
    if path is None or not path.is_file():
        raise UserError(f"no calibration ships with sensor profile {profile_or_path!r}")
    info = read_record(path, load=False).meta.get(SHIPPED_ATTR)
    if not info:
        raise UserError(f"{path}: not a shipped calibration (no {SHIPPED_ATTR!r} attribute)")
    return dict(info)


def shipped_note(profile_or_path) -> str:
    """The line ``live`` and ``reconstruct`` print when they use a shipped calibration: what it
    is built from, its licence and the error measured on another unit.

    >>> print(shipped_note("digit"))    # doctest: +ELLIPSIS
    shipped DIGIT calibration (.../digit.calibration.h5; built from 20 presses of one unit, MIT licence, ...): on another unit expect about ... deg mean normal error (measured on an altered copy of its 10 held-out presses: ...; ... deg on the unit itself); calibrate your own unit for better (docs/calibration.md)
    """
    info = shipped_info(profile_or_path)
    path = Path(profile_or_path) if str(profile_or_path).endswith(".h5") else \
        shipped_calibration_path(profile_or_path)
    orig, alt = info["original"], info["altered"]
    return (f"shipped {info['sensor']} calibration ({path}; built from {info['presses']} presses of one unit, "
            f"{info['licence']} licence, {info['attribution']}): on another unit expect about "
            f"{alt['mean_deg']:.1f} deg mean normal error (measured on an altered copy of its {orig['presses']} "
            f"held-out presses: {alt['alteration']}; {orig['mean_deg']:.1f} deg on the unit itself); "
            "calibrate your own unit for better (docs/calibration.md)")
