"""The identity of a record as the input of a computation, the one rule every entry point uses.

- a store entry (read from ``<store>/<stage>/<key>.h5``) is identified by its stage key, so
  a result computed by ``iristac run`` and read back by ``iristac reconstruct`` is the same
  input to both;
- any other file by the hash of its content (``file:...``, :func:`file_input_key`), so
  renaming, moving or copying it out of a store changes nothing;
- a record in memory by the digest of its content (``memory:...``).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from pipeline.base.errors import UserError
from pipeline.base.store import Record

__all__ = ["record_key", "is_entry", "file_input_key"]


def record_key(rec: Record) -> str:
    """The identity of a record as a stage input (see the module docstring).

    Examples
    --------
    >>> import numpy as np
    >>> rec = Record("depth", {"height": np.zeros((1, 2, 2), np.float32), "mask": np.ones((1, 2, 2), bool)},
    ...              {"integrator": "fc", "mm_per_px": 0.1})
    >>> record_key(rec)[:7]
    'memory:'
    """
    if is_entry(rec):
        return str(rec.provenance["iristac_key"])
    if rec.path is None:  # an in-memory record: hash its content
        from pipeline.base.hashing import digest

        return "memory:" + digest({"schema": rec.schema, "data": rec.data, "meta": rec.meta})
    return file_input_key(rec.path)


def is_entry(rec: Record) -> bool:
    """Whether ``rec`` was read from (or written to) its own entry of a stage store."""
    key = rec.provenance.get("iristac_key") if rec.provenance else None
    return bool(key) and rec.path is not None and Path(rec.path).stem == key \
        and Path(rec.path).parent.name == rec.provenance.get("iristac_stage")


def file_input_key(path: str | os.PathLike) -> str:
    """Content hash of a file outside the store (``file:`` + 32 hex digits)."""
    p = Path(path)
    if not p.is_file():
        raise UserError(f"{p}: no such file")
    h = hashlib.sha256()
    with open(p, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return "file:" + h.hexdigest()[:32]
