"""Shape checks and conversion of solver inputs (numpy or torch) to flattened arrays.

``device`` None: numpy arrays on the CPU; a device: torch tensors there
(:mod:`pipeline.normals._xp`).
"""

from __future__ import annotations

import numpy as np

from pipeline.normals import _xp
from pipeline.normals._xp import Array


def check_observations(observations, name: str) -> tuple[int, int, int]:
    """Return ``(N, H, W)`` of observations ``(N, H, W)`` or raise with the shape received."""
    shape = tuple(observations.shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"{name}: observations must have shape (N_obs, H, W), got {shape}")
    return shape  # type: ignore[return-value]


def check_lights(lights, n: int, hw: tuple[int, int] | None, name: str) -> bool:
    """Validate ``(N, 3)`` or ``(N, H, W, 3)`` lights; return True when they are per pixel."""
    shape = tuple(lights.shape)
    if len(shape) == 2 and shape == (n, 3):
        return False
    if len(shape) == 4 and shape[0] == n and shape[3] == 3 and (hw is None or shape[1:3] == tuple(hw)):
        return True
    want = f"({n}, 3) or ({n}, H, W, 3)" if hw is None else f"({n}, 3) or ({n}, {hw[0]}, {hw[1]}, 3)"
    raise ValueError(f"{name}: lights must have shape {want}, got {shape}")


def check_stack(observations, lights, groups, device, dtype, name: str):
    """The checks every per-pixel solver starts with: ``(N, H, W)`` observations, lights of
    matching shape, albedo groups. Returns ``(N, H, W, device, dtype, groups, num_groups)``
    with a ``torch.device`` and torch dtype (the solvers that call it are torch)."""
    import torch

    N, H, W = check_observations(observations, name)
    check_lights(lights, N, (H, W), name)
    dev = torch.device(device)
    g, num_groups = check_groups(groups, N, name, dev)
    return N, H, W, dev, _xp.float_dtype(dtype, dev), g, num_groups


def check_groups(groups, n: int, name: str, device) -> tuple[Array | None, int]:
    """Albedo group id per observation ``(N,)`` -> (int64 array, or long tensor on ``device``;
    number of groups)."""
    if groups is None:
        return None, 1
    g = np.asarray(groups)
    if g.shape != (n,) or g.dtype.kind not in "iu" or (g.size and g.min() < 0):
        raise ValueError(f"{name}: groups must be non-negative integers of shape ({n},), got "
                         f"{g.shape} {g.dtype}")
    return _xp.integers(g.astype(np.int64), device), int(g.max()) + 1 if g.size else 1


#: Pixels per chunk of the real-time paths: a chunk's float observations (N x CHUNK) stay in
#: the CPU cache between the passes (conversion, moments, solve), instead of streaming the
#: whole frame through memory for each pass.
CHUNK = 80000


def is_integer(x) -> bool:
    """Whether ``x`` (numpy or torch) holds integers (cannot be NaN/Inf)."""
    if _xp.is_tensor(x):
        return not (x.dtype.is_floating_point or x.dtype.is_complex)
    return np.asarray(x).dtype.kind in "iub"


def chunks(M: int, device) -> list[tuple[int, int]]:
    """Pixel ranges for the chunked paths (one range on a GPU, where chunking only costs;
    ``device`` None is the CPU)."""
    if str(device if device is not None else "cpu").split(":")[0] != "cpu" or M <= CHUNK:
        return [(0, M)]
    n = -(-M // CHUNK)
    step = -(-M // n)  # balanced: no small tail chunk
    return [(a, min(a + step, M)) for a in range(0, M, step)]


def flatten_observations(observations, dtype, device) -> tuple[Array, Array | None]:
    """``(N, H, W)`` -> ``(N, H*W)`` array, and the finite mask (None when all finite).

    Integer images cannot hold NaN, so they skip the finiteness pass (the real-time path).
    Non-finite values are replaced by 0; the caller gives them zero weight.
    """
    integer = is_integer(observations)
    I = _xp.asarray(observations, dtype, device)
    I = I.reshape(I.shape[0], -1)
    if integer:
        return I, None
    xp = _xp.namespace(I)
    finite = xp.isfinite(I)
    if bool(finite.all()):
        return I, None
    return xp.where(finite, I, 0.0), finite


def flatten_lights(lights, dtype, device) -> tuple[Array, Array]:
    """Lights -> (array ``(N, 3)`` or ``(N, 3, H*W)``, usable mask ``(N,)`` or ``(N, H*W)``).

    Non-finite light vectors are zeroed and marked unusable, so a hole in a calibration
    masks pixels instead of spreading NaN.
    """
    L = _xp.asarray(lights, dtype, device)
    xp = _xp.namespace(L)
    if L.ndim == 4:
        L = _xp.contiguous(L.reshape(L.shape[0], -1, 3).swapaxes(1, 2))
        ok = xp.isfinite(L).all(1)
        L = xp.where(ok[:, None, :], L, 0.0)
    else:
        ok = xp.isfinite(L).all(-1)
        L = xp.where(ok[:, None], L, 0.0)
    return L, ok


def group_counts_ok(groups: Array | None, num_groups: int, min_count: int = 3) -> bool:
    """True when every albedo group has at least ``min_count`` observations (so per-group
    albedo can be separated from the normal)."""
    if groups is None or num_groups < 2:
        return False
    counts = _xp.namespace(groups).bincount(groups, minlength=num_groups)
    return bool((counts >= min_count).all())
