"""Thin bridge between calibration and the project's stage store.

Calibration reads and writes standalone records (``capture.h5``, ``calibration.h5``,
``illumination.h5``) only through :mod:`pipeline.store` (``read_record`` / ``write_record``),
which validates them against ``data_schemas/stages/<schema>.json``. Its errors
(:class:`pipeline.store.StoreError`) are :class:`pipeline.errors.UserError`: the CLI prints
them as one line naming the file and the problem.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import UserError
from pipeline.store import Record, read_record, write_record

__all__ = ["write", "read"]


def write(path: str | Path, schema: str, data: dict[str, np.ndarray], meta: dict[str, Any]) -> Path:
    """Write a standalone ``schema`` record: datasets ``data`` (path -> array) and attributes ``meta``."""
    path = Path(path)
    write_record(path, Record(schema=schema, data=data, meta=meta))
    return path


def read(path: str | Path, schema: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a standalone ``schema`` record; returns ``(data, meta)``. Bad files raise :class:`UserError`."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file (expected a '{schema}' HDF5 record)")
    rec = read_record(path, schema=schema)
    return dict(rec.data), dict(rec.meta)
