"""Which arrays a least-squares solve runs on: numpy on the CPU, torch for tensors and devices.

The least-squares code (:mod:`pipeline.normals._lstsq`, :mod:`pipeline.normals._linalg3`,
:mod:`pipeline.normals._inputs`) is written once, against what numpy and torch spell alike:
``where``, ``sqrt``, ``stack``, ``isfinite``, ``nan_to_num``, ``clip``, ``arccos``, ``cos``,
``finfo``, ``bincount``, ``concatenate``, ``broadcast_to``, ``*_like`` constructors,
reductions with ``keepdims``, ``@``, ``swapaxes``, indexing and slicing. A function asks
:func:`namespace` which library its input belongs to; this module holds the few things the two
spell differently (a dtype conversion, an array on a device, a copy out to numpy) and the rule
for which library a solve uses (:func:`solve_device`).

Nothing here imports torch unless a tensor or a device is asked for: a tensor exists only once
torch is imported, and ``device=None`` means numpy arrays on the CPU. A CPU solve through
:class:`pipeline.normals.FarFieldSolver` therefore never pays torch's import (1-3 s of a
one-shot ``reconstruct``; ``docs/reconstruction.md``).

Examples
--------
>>> a = asarray([[1, 2], [3, 4]], "float32")            # no device: numpy
>>> namespace(a).__name__, a.dtype.name
('numpy', 'float32')
>>> solve_device("cpu"), solve_device("cpu", compile=True).type
(None, 'cpu')
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from pipeline.base.pixel_mask import is_tensor  # the one definition, below the solvers and the integrators

__all__ = ["Array", "is_tensor", "namespace", "solve_device", "float_dtype", "numpy_dtype", "asarray", "integers",
           "astype", "to_numpy", "pixels_first", "full", "contiguous", "index_like"]

#: A numpy array or a torch tensor (the functions written against both take either).
Array = Any


def namespace(x):
    """The library of ``x``: the ``torch`` module for a tensor, else ``numpy``."""
    return sys.modules["torch"] if is_tensor(x) else np


def solve_device(device, compile: bool = False):
    """Where a solve runs: None (numpy on the CPU) for ``device="cpu"``, else the
    ``torch.device`` (any other device, or ``compile``: ``torch.compile`` needs tensors).

    ``device`` is a string (``"cpu"``, ``"cuda"``, ``"cuda:1"``) or a ``torch.device``.
    """
    if not compile and str(device).split(":")[0] == "cpu":
        return None
    import torch

    return torch.device(device)


def float_dtype(dtype, device=None):
    """``"float32"``, ``np.float64``, ``torch.float32`` ... -> numpy's float dtype (``device``
    None) or torch's (a device).

    Examples
    --------
    >>> float_dtype("float64"), float_dtype(np.float32)
    (dtype('float64'), dtype('float32'))
    """
    out = numpy_dtype(dtype)
    if out not in (np.float32, np.float64):
        raise ValueError(f"dtype must be float32 or float64, got {dtype!r}")
    if device is None:
        return out
    import torch

    return getattr(torch, out.name)


def numpy_dtype(dtype) -> np.dtype | None:
    """numpy's dtype of a numpy or torch dtype (``torch.float32`` -> ``float32``); None when
    there is none."""
    for spec in (dtype, str(dtype).removeprefix("torch.")):
        try:
            return np.dtype(spec)
        except TypeError:
            continue
    return None


def to_numpy(x) -> np.ndarray:
    """A numpy array of ``x`` (a tensor is copied to the CPU, a numpy array is not copied)."""
    return x.detach().cpu().numpy() if is_tensor(x) else np.asarray(x)


def asarray(x, dtype, device=None) -> Array:
    """A numeric array or tensor -> floating ``dtype``: numpy (``device`` None) or a tensor on
    ``device`` (no copy when possible)."""
    if device is None:
        a = to_numpy(x)
        _check_numeric(a)
        return a.astype(float_dtype(dtype), copy=False)
    import torch

    if isinstance(x, torch.Tensor):
        return x.to(device=device, dtype=float_dtype(dtype, device))
    a = np.asarray(x)
    _check_numeric(a)
    if a.dtype == np.uint16 or a.dtype == np.uint32:
        a = a.astype(np.int64)  # torch has no unsigned 16/32-bit arithmetic on every build
    if not a.flags.writeable:
        a = np.array(a)  # torch refuses read-only (e.g. broadcast) arrays without copying
    return torch.as_tensor(a, device=device).to(float_dtype(dtype, device))


def _check_numeric(a: np.ndarray) -> None:
    if a.dtype.kind not in "fiub":
        raise ValueError(f"expected a numeric array, got dtype {a.dtype}")


def integers(x, device=None) -> Array:
    """An integer array as numpy (``device`` None) or a tensor on ``device``, values not yet
    converted (the chunked paths convert a chunk at a time)."""
    if device is None:
        return to_numpy(x)
    import torch

    if isinstance(x, torch.Tensor):
        return x.to(device)
    a = np.asarray(x)
    if a.dtype == np.uint16:
        a = a.astype(np.int32)  # torch lacks arithmetic on uint16; int32 holds it at half int64's traffic
    elif a.dtype in (np.uint32, np.uint64):
        a = a.astype(np.int64)  # torch lacks arithmetic on these unsigned types
    if not a.flags.writeable:
        a = np.array(a)
    return torch.as_tensor(a, device=device)


def astype(x, dtype) -> Array:
    """``x`` as ``dtype`` (of its own library); no copy when it already is."""
    return x.to(dtype) if is_tensor(x) else x.astype(dtype, copy=False)


def contiguous(x) -> Array:
    """A C-contiguous copy of ``x`` (no copy when it already is)."""
    return x.contiguous() if is_tensor(x) else np.ascontiguousarray(x)


def full(like, shape, value, dtype) -> Array:
    """An array of ``shape`` filled with ``value``, in ``like``'s library (and on its device)."""
    if is_tensor(like):
        return sys.modules["torch"].full(shape, value, dtype=dtype, device=like.device)
    return np.full(shape, value, dtype=dtype)


def index_like(like, idx: np.ndarray) -> Array:
    """Integer indices ``idx`` for indexing arrays of ``like``'s library (on its device)."""
    return sys.modules["torch"].as_tensor(idx, device=like.device) if is_tensor(like) else idx


def pixels_first(x) -> np.ndarray:
    """``(M,)`` or ``(K, M)`` (pixels last) -> a contiguous numpy ``(M,)`` or ``(M, K)``."""
    if is_tensor(x):  # one transposing copy made by torch (on the device), then to the host
        x = x.detach()
        return (x.T.contiguous() if x.dim() == 2 else x).cpu().numpy()
    return np.ascontiguousarray(x.T if x.ndim == 2 else x)
