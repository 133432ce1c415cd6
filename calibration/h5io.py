"""Thin bridge between calibration and the project's stage store.

Calibration reads and writes standalone records (``capture.h5``, ``calibration.h5``) through
:mod:`pipeline.store` (``read_record`` / ``write_record``), which validates them against
``data_schemas/stages/<schema>.json``. While that store is not available in this checkout
the same layout (datasets by path, attributes with JSON for containers) is written with h5py
directly, atomically, so that files stay readable by the store once it lands.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import UserError

__all__ = ["write", "read"]


def _store():
    try:
        from pipeline import store  # noqa: F401
    except ImportError:
        return None
    return store


def write(path: str | Path, schema: str, data: dict[str, np.ndarray], meta: dict[str, Any]) -> Path:
    """Write a standalone record: datasets ``data`` (path -> array) and attributes ``meta``."""
    path = Path(path)
    store = _store()
    if store is not None:
        store.write_record(path, store.Record(schema=schema, data=data, meta=meta))
        return path
    import h5py

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name, suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as f:
            for k, v in data.items():
                f.create_dataset(k, data=np.asarray(v))
            f.attrs["iristac_schema"] = schema
            for k, v in meta.items():
                f.attrs[k] = v if isinstance(v, (int, float, str, bool, np.generic)) else json.dumps(v)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def read(path: str | Path, schema: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a standalone record; returns ``(data, meta)``. Bad files raise :class:`UserError`."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file (expected a '{schema}' HDF5 record)")
    store = _store()
    if store is not None:
        try:
            rec = store.read_record(path, schema=schema)
        except store.StoreError as exc:
            raise UserError(str(exc)) from None
        return dict(rec.data), dict(rec.meta)
    import h5py

    data: dict[str, np.ndarray] = {}
    try:
        with h5py.File(path, "r") as f:
            got = f.attrs.get("iristac_schema")
            if got is not None and str(got) != schema:
                raise UserError(f"{path}: attribute iristac_schema is '{got}', expected '{schema}'")
            f.visititems(lambda name, obj: data.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
            meta = {}
            for k, v in f.attrs.items():
                if isinstance(v, bytes):
                    v = v.decode()
                if isinstance(v, str) and v[:1] in "[{":
                    try:
                        v = json.loads(v)
                    except ValueError:
                        pass
                meta[k] = v.item() if isinstance(v, np.generic) else v
    except OSError as exc:
        raise UserError(f"{path}: not a readable HDF5 file ({exc})") from None
    meta.pop("iristac_schema", None)
    return data, meta
