"""Canonical encoding and hashing of stage parameters, so equal inputs give equal cache keys.

The encoding is JSON with sorted keys and no whitespace. Tuples become lists, numpy scalars
become Python numbers, and numpy arrays become ``{"__ndarray__": sha256, "dtype", "shape"}``
so that arrays hash by content, dtype and shape without putting megabytes into the key.
Non-finite floats are encoded as strings, since JSON has no NaN.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import PurePath
from typing import Any, Mapping

import numpy as np

__all__ = ["canonical", "canonical_json", "digest"]


def _array_token(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    h = hashlib.sha256()
    h.update(str(a.dtype.str).encode())
    h.update(repr(a.shape).encode())
    h.update(a.tobytes())
    return {"__ndarray__": h.hexdigest(), "dtype": a.dtype.str, "shape": list(a.shape)}


def canonical(obj: Any) -> Any:
    """Return a JSON-ready structure that is equal for equal parameters.

    Examples
    --------
    >>> canonical({"b": (1, 2), "a": np.float32(0.5)})
    {'a': 0.5, 'b': [1, 2]}
    """
    if isinstance(obj, Mapping):
        out = {}
        for k in sorted(obj, key=str):
            if not isinstance(k, str):
                raise TypeError(f"parameter keys must be strings, got {k!r} ({type(k).__name__})")
            out[k] = canonical(obj[k])
        return out
    if isinstance(obj, (list, tuple)):
        return [canonical(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _array_token(obj)
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else repr(f)
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, PurePath):
        return str(obj)
    raise TypeError(f"cannot use a {type(obj).__name__} as a stage parameter: {obj!r}")


def canonical_json(obj: Any) -> str:
    """Canonical JSON text of ``obj`` (see :func:`canonical`).

    Examples
    --------
    >>> canonical_json({"b": 1, "a": [1.0, None]})
    '{"a":[1.0,null],"b":1}'
    """
    return json.dumps(canonical(obj), sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def digest(obj: Any, length: int = 32) -> str:
    """Hex SHA-256 of the canonical JSON of ``obj``, truncated to ``length`` characters."""
    return hashlib.sha256(canonical_json(obj).encode("ascii")).hexdigest()[:length]
