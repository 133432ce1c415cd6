"""Shape checks and conversion of solver inputs (numpy or torch) to flattened tensors."""

from __future__ import annotations

import numpy as np
import torch

from pipeline.normals import _torch as T


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
    matching shape, albedo groups. Returns ``(N, H, W, device, dtype, groups, num_groups)``."""
    N, H, W = check_observations(observations, name)
    check_lights(lights, N, (H, W), name)
    dev = torch.device(device)
    g, num_groups = check_groups(groups, N, name, dev)
    return N, H, W, dev, T.torch_dtype(dtype), g, num_groups


def check_groups(groups, n: int, name: str, device) -> tuple[torch.Tensor | None, int]:
    """Albedo group id per observation ``(N,)`` -> (long tensor, number of groups)."""
    if groups is None:
        return None, 1
    g = np.asarray(groups)
    if g.shape != (n,) or g.dtype.kind not in "iu" or (g.size and g.min() < 0):
        raise ValueError(f"{name}: groups must be non-negative integers of shape ({n},), got "
                         f"{g.shape} {g.dtype}")
    return torch.as_tensor(g.astype(np.int64), device=device), int(g.max()) + 1 if g.size else 1


#: Pixels per chunk of the real-time paths: a chunk's float observations (N x CHUNK) stay in
#: the CPU cache between the passes (conversion, moments, solve), instead of streaming the
#: whole frame through memory for each pass.
CHUNK = 80000


def is_integer(x) -> bool:
    """Whether ``x`` (numpy or torch) holds integers (cannot be NaN/Inf)."""
    if isinstance(x, torch.Tensor):
        return not (x.dtype.is_floating_point or x.dtype.is_complex)
    return np.asarray(x).dtype.kind in "iub"


def integer_tensor(x, device) -> torch.Tensor:
    """An integer array as a tensor on ``device`` without converting its values yet."""
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


def chunks(M: int, device) -> list[tuple[int, int]]:
    """Pixel ranges for the chunked paths (one range on a GPU, where chunking only costs)."""
    if torch.device(device).type != "cpu" or M <= CHUNK:
        return [(0, M)]
    n = -(-M // CHUNK)
    step = -(-M // n)  # balanced: no small tail chunk
    return [(a, min(a + step, M)) for a in range(0, M, step)]


def flatten_observations(observations, dtype, device) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(N, H, W)`` -> ``(N, H*W)`` tensor, and the finite mask (None when all finite).

    Integer images cannot hold NaN, so they skip the finiteness pass (the real-time path).
    Non-finite values are replaced by 0; the caller gives them zero weight.
    """
    integer = (observations.dtype.is_floating_point is False) if isinstance(observations, torch.Tensor) \
        else np.asarray(observations).dtype.kind in "iub"
    I = T.to_tensor(observations, dtype, device)
    I = I.reshape(I.shape[0], -1)
    if integer:
        return I, None
    finite = torch.isfinite(I)
    if bool(finite.all()):
        return I, None
    return torch.where(finite, I, torch.zeros((), dtype=dtype, device=device)), finite


def flatten_lights(lights, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Lights -> (tensor ``(N, 3)`` or ``(N, 3, H*W)``, usable mask ``(N,)`` or ``(N, H*W)``).

    Non-finite light vectors are zeroed and marked unusable, so a hole in a calibration
    masks pixels instead of spreading NaN.
    """
    L = T.to_tensor(lights, dtype, device)
    if L.dim() == 4:
        L = L.reshape(L.shape[0], -1, 3).permute(0, 2, 1).contiguous()
        ok = torch.isfinite(L).all(1)
        L = torch.where(ok[:, None, :], L, torch.zeros((), dtype=dtype, device=device))
    else:
        ok = torch.isfinite(L).all(-1)
        L = torch.where(ok[:, None], L, torch.zeros((), dtype=dtype, device=device))
    return L, ok


def group_counts_ok(groups: torch.Tensor | None, num_groups: int, min_count: int = 3) -> bool:
    """True when every albedo group has at least ``min_count`` observations (so per-group
    albedo can be separated from the normal)."""
    if groups is None or num_groups < 2:
        return False
    counts = torch.bincount(groups, minlength=num_groups)
    return bool((counts >= min_count).all())
