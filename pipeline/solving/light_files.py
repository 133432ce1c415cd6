"""The light model of a capture's frames, from whichever file holds it.

Where the lights come from (:func:`load_lights`, for a capture :func:`capture_lights`; first that
applies):

- ``calibration``: ``light_field (P, C, H, W, 3)`` (with optional ``flat_field (P, C, H, W)``
  by which observations are divided first), ``light_vectors (P, C, 3)`` (far field) and every
  fitted model ``models/<name>/*`` (:func:`calibration.stored.calibration_from_record`; the
  ``far``, ``near``, ``traced``, ``lut`` and ``mlp`` solvers apply them,
  :mod:`pipeline.solving.model_solvers`);
- ``illumination``: ``light_matrices (P, 3, H, W, 3)``, or ``V (L, H, W, 3)`` combined with
  the capture's ``drive``, ``brightness`` and ``exposure`` (and ``gains (L,)`` or ``(L, 3)``
  if the file has them) by :func:`sim.illumination_model.light_matrices`;
- the capture itself: ``lights/light_vectors (P, C, 3)`` (written by the DiLiGenT importer).

The result is a :class:`pipeline.normals.lights.LightSource`, keyed by the light file's identity
(:func:`pipeline.base.identity.record_key`). The normals stage, the streaming reconstruction and
``iristac live`` all load their lights here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.identity import record_key
from pipeline.normals.lights import LightSource

__all__ = ["load_lights", "capture_lights"]


def _check_shape(arr, want: tuple, path, name: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.shape != want:
        raise UserError(f"{path}: dataset {name!r} has shape {a.shape}, expected {want} to match the capture")
    return a


def load_lights(calibration=None, illumination=None, *, mode, shape, channels: int = 3, exposure: float = 1.0,
                embedded=None, where: str = "frames") -> LightSource:
    """The light model for frames of ``shape`` under ``mode``'s patterns (see the module docstring).

    Parameters
    ----------
    calibration, illumination : Record, optional
        At most one: the light file.
    mode : LightingMode
        The patterns (``drive (P, L, 3)``, ``brightness (P,)``: anything with both, such as a
        capture's own, :func:`capture_lights`); an illumination's ``V`` is combined with them.
    shape : (H, W)
        The frames' image size; ``channels`` their camera channels.
    exposure : float
        The frames' exposure (an illumination's light matrices scale with it).
    embedded : ndarray, shape (P, C, 3), optional
        Far-field lights that came with the frames (a capture's ``lights/light_vectors``), used
        when neither file is given.
    where : str
        The frames' name (a capture file) for messages and the light source's name.
    """
    drive = np.asarray(mode.drive)
    P, (H, W), C = drive.shape[0], tuple(int(s) for s in shape), int(channels)
    if calibration is not None and illumination is not None:
        raise UserError("give either a calibration or an illumination file, not both")
    if calibration is not None:
        return _calibration_lights(calibration, P, H, W, C)
    if illumination is not None:
        return _illumination_lights(illumination, mode, exposure, P, H, W, C)
    if embedded is not None:
        src = LightSource(source=f"capture:{Path(where).name}:lights/light_vectors", key="embedded")
        src.far = _check_shape(embedded, (P, C, 3), where, "lights/light_vectors")
        return src
    raise UserError(f"{where}: no light model: pass --calibration or --illumination "
                    f"(the capture has no embedded lights/light_vectors)")


def capture_lights(capture, calibration=None, illumination=None) -> LightSource:
    """:func:`load_lights` for a ``capture`` Record: its patterns, image size, channels, exposure
    and embedded far-field lights (``lights/light_vectors``, written by importers)."""
    from types import SimpleNamespace

    _, P, H, W, C = capture.data["frames"].shape
    patterns = SimpleNamespace(drive=capture.data["drive"], brightness=capture.data.get("brightness"))
    return load_lights(calibration, illumination, mode=patterns, shape=(H, W), channels=C,
                       exposure=float(capture.meta.get("exposure", 1.0)),
                       embedded=capture.data.get("lights/light_vectors"), where=str(capture.path or "memory"))


def _calibration_lights(calibration, P: int, H: int, W: int, C: int) -> LightSource:
    d, path = calibration.data, calibration.path
    src = LightSource(source=f"calibration:{Path(path).name if path else 'memory'}", key=record_key(calibration))
    if "light_field" in d:
        src.field = _check_shape(d["light_field"], (P, C, H, W, 3), path, "light_field")
        if "flat_field" in d:
            src.flat_field = _check_shape(d["flat_field"], (P, C, H, W), path, "flat_field")
    if "light_vectors" in d:
        src.far = _check_shape(d["light_vectors"], (P, C, 3), path, "light_vectors")
    if any(k.startswith("models/") for k in d):
        from calibration.stored import calibration_from_record

        src.models, cal_meta = calibration_from_record(calibration)
        src.markers = cal_meta.get("markers")
        _check_model_shapes(src.models, (P, H, W, C), path)
    if src.field is None and src.far is None and not src.models:
        raise UserError(f"{path}: calibration has no light model (expected dataset 'light_field', "
                        f"'light_vectors' or 'models/<name>/*')")
    return src


def _illumination_lights(illumination, mode, exposure: float, P: int, H: int, W: int, C: int) -> LightSource:
    from sim.illumination_model import light_matrices

    d, path = illumination.data, illumination.path
    src = LightSource(source=f"illumination:{Path(path).name if path else 'memory'}", key=record_key(illumination))
    if "light_matrices" in d and d["light_matrices"].shape[0] == P:
        src.field = _check_shape(d["light_matrices"], (P, C, H, W, 3), path, "light_matrices")
        return src
    V = np.asarray(d["V"])
    if V.shape[1:3] != (H, W):
        raise UserError(f"{path}: dataset 'V' covers {V.shape[1:3]} pixels, the capture has {(H, W)}")
    drive = np.asarray(mode.drive)
    if drive.shape[1] != V.shape[0]:
        raise UserError(f"{path}: 'V' has {V.shape[0]} LEDs but the capture's drive has {drive.shape[1]}")
    if C != 3:
        raise UserError(f"{path}: illumination light matrices need 3 camera channels, the capture has {C}")
    src.field = light_matrices(V, drive, mode.brightness, float(exposure), d.get("gains"))
    return src


def _check_model_shapes(models, want: tuple, path) -> None:
    """A model made for other frames (size, patterns, channels) is one clear error, not a
    broadcast failure deep inside it."""
    P, H, W, C = want
    for name, m in models.items():
        ref = m.stored_reference() if hasattr(m, "stored_reference") else None
        field = getattr(m, "field", None)
        have = ref.shape if ref is not None else (None if field is None else
                                                   (field.shape[0], field.shape[2], field.shape[3], field.shape[1]))
        if have is not None and tuple(have) != (P, H, W, C):
            raise UserError(f"{path}: model '{name}' was calibrated for {have[0]} pattern(s) x {have[1]}x{have[2]} px "
                            f"x {have[3]} channel(s), the capture has {P} x {H}x{W} px x {C}")
