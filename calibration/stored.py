"""Fitted models back from ``calibration.h5``: every model :func:`calibrate` saved, ready to predict.

``CalibrationResult.save`` writes each model's arrays under ``models/<name>/``; light-field
models (far, near, traced) also their per-pixel ``light_field (P, C, H, W, 3)`` (and the
far-field model its ``flat_field``), which is all a prediction needs, so they come back as
:class:`StoredLightField`. The LUT and the MLP come back through their ``from_arrays``.
Every returned model has the batched API of :mod:`calibration.normal_maps`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from calibration.models.base import LightFieldModel
from pipeline.base.errors import UserError

__all__ = ["StoredLightField", "load_models", "load_calibration", "calibration_from_record"]


class StoredLightField(LightFieldModel):
    """A light-field model given by its per-pixel light vectors.

    Parameters
    ----------
    name : str
    light_field : ndarray, shape (P, C, H, W, 3)
    flat_field : ndarray, shape (P, C, H, W), optional
    """

    def __init__(self, name: str, light_field: np.ndarray, flat_field: np.ndarray | None = None):
        lf = np.asarray(light_field, np.float32)
        if lf.ndim != 5 or lf.shape[-1] != 3:
            raise ValueError(f"StoredLightField: light_field must be (P, C, H, W, 3), got {lf.shape}")
        self.name = name
        self.field = lf
        self.num_patterns, self.num_channels = lf.shape[:2]
        self.flat = None if flat_field is None else np.asarray(flat_field, np.float32)
        if self.flat is not None and self.flat.shape != lf.shape[:4]:
            raise ValueError(f"StoredLightField: flat_field must be {lf.shape[:4]}, got {self.flat.shape}")

    def lights_at(self, rows, cols, shape):
        if tuple(shape) != self.field.shape[2:4]:
            raise ValueError(f"{self.name}: the light field is {self.field.shape[2:4]} pixels, the frames {tuple(shape)}")
        L = self.field[:, :, rows, cols]  # (P, C, N, 3)
        return np.moveaxis(L.reshape(-1, len(rows), 3), 1, 0).astype(np.float64)

    def light_field(self, shape):
        return self.field

    def fit(self, samples, reference=None):  # pragma: no cover - stored models are fitted already
        raise TypeError(f"{self.name}: a stored light field is already fitted")

    def to_arrays(self) -> dict[str, np.ndarray]:
        out = {"light_field": self.field}
        if self.flat is not None:
            out["flat_field"] = self.flat
        return out


def load_calibration(path: str | Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(models, meta)`` of a calibration.h5: name -> fitted model, and the file's attributes
    (plus ``meta["markers"]``, an (H, W) bool array, when the calibration has a marker mask)."""
    from pipeline.base.store import read_record

    if not Path(path).is_file():
        raise UserError(f"{path}: no such file (expected a 'calibration' HDF5 record from iristac calibrate)")
    return calibration_from_record(read_record(path, schema="calibration"))


def calibration_from_record(rec) -> tuple[dict[str, Any], dict[str, Any]]:
    """:func:`load_calibration` of a ``calibration`` Record already read (or made in memory)."""
    path = rec.path if rec.path is not None else "calibration"
    data, meta = dict(rec.data), dict(rec.meta)
    if "markers" in data:  # the printed gel markers the calibration filled in (CalibrationResult.markers)
        meta["markers"] = np.asarray(data["markers"]).astype(bool)
    groups: dict[str, dict[str, np.ndarray]] = {}
    for key, arr in data.items():
        if key.startswith("models/"):
            _, name, rest = key.split("/", 2)
            groups.setdefault(name, {})[rest] = arr
    models: dict[str, Any] = {}
    for name, arrays in groups.items():
        gain, max_tilt = arrays.pop("tilt_gain", None), arrays.pop("max_tilt", None)
        try:
            models[name] = _model_from_arrays(name, arrays)
            # The output correction calibrate fitted (CalibrationModel.output_arrays).
            models[name].tilt_gain = 1.0 if gain is None else float(gain)
            models[name].max_tilt = None if max_tilt is None else float(max_tilt)
        except (KeyError, ValueError) as exc:
            raise UserError(f"{path}: model '{name}' cannot be read back ({exc}; datasets models/{name}/"
                            f"{{{', '.join(sorted(arrays))}}})") from None
    return models, meta


def load_models(path: str | Path) -> dict[str, Any]:
    """Every fitted model of a calibration.h5, name -> model (see the module docstring)."""
    return load_calibration(path)[0]


def _model_from_arrays(name: str, arrays: dict[str, np.ndarray]):
    if name == "lut":
        from calibration.models.lut import LUTModel

        return LUTModel.from_arrays(arrays)
    if name in ("conv", "conv-fast"):
        from calibration.models.conv import CONV_MODELS

        return CONV_MODELS[name].from_arrays(arrays)
    if name == "mlp":
        from calibration.models.mlp import MLPModel

        return MLPModel.from_arrays(arrays)
    if "light_field" in arrays:
        flat = arrays.get("flat_field")
        return StoredLightField(name, arrays["light_field"], None if flat is None else flat)
    raise KeyError("light_field")
