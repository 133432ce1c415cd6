"""Solve only where asked: gather a mask's pixels once, solve them in batches, scatter back.

A photometric-stereo object (a DiLiGenT capture: 15.8k object pixels in a 612 x 512 frame)
or a user's region of interest covers a small part of the image. Every solver takes
``mask=`` and goes through :class:`PixelMask`: the masked pixels of the observations (and of
per-pixel lights) are gathered into a ``(N, 1, M)`` "image" of ``M`` pixels, the solver runs
on that, and :meth:`PixelMask.scatter` puts the result back into the full frame, with every
pixel outside the mask marked invalid: ``mask`` False, ``count`` 0 (no observation used, the
confidence), flat normal ``(0, 0, 1)``, albedo and residual 0, condition at the cap. No NaN.

This module is the one place that does it, so every solver's masked result has the same
layout (tests compare each solver's masked result with its full-frame one on the mask).
:func:`pixel_batches` splits a long pixel axis into batches that bound a solver's
temporaries (``N x batch`` floats each).
"""

from __future__ import annotations

import functools

import numpy as np

from pipeline.normals._xp import is_tensor
from pipeline.normals.result import COND_CAP, NormalResult

__all__ = ["PixelMask", "masked_solve", "solves_in_mask", "pixel_batches", "BATCH_ELEMENTS"]

#: Elements (observations x pixels) of one batch: 8 M floats = 32 MB per float32 temporary.
BATCH_ELEMENTS = 1 << 23


class PixelMask:
    """The pixels of a boolean mask: gather them from any array, scatter results back.

    Parameters
    ----------
    mask : array_like, shape (H, W)
        Pixels to solve (bool, or numbers: non-zero is True).
    shape : (H, W)
        The image size the mask must have.
    name : str
        Who is asking (the function, or the file the mask came from): errors start with it.

    Raises
    ------
    ValueError
        A mask of the wrong shape, non-finite values, or a mask that selects no pixel.

    Examples
    --------
    >>> pm = PixelMask([[True, False], [False, True]], (2, 2), "demo")
    >>> pm.count, pm.gather(np.arange(8).reshape(2, 2, 2), axis=1).tolist()
    (2, [[[0, 3]], [[4, 7]]])
    >>> PixelMask(np.zeros((2, 2)), (2, 2), "demo")
    Traceback (most recent call last):
    ...
    ValueError: demo: the mask selects no pixels
    """

    def __init__(self, mask, shape: tuple[int, int], name: str = "mask"):
        m = mask.detach().cpu().numpy() if is_tensor(mask) else np.asarray(mask)
        shape = tuple(int(s) for s in shape)
        if m.shape != shape:
            raise ValueError(f"{name}: mask must have shape {shape} (the image's H, W), got {m.shape}")
        if m.dtype != bool:
            if m.dtype.kind not in "iuf" or (m.dtype.kind == "f" and not np.isfinite(m).all()):
                raise ValueError(f"{name}: mask must be boolean (or finite numbers, non-zero = True), got {m.dtype}")
            m = m != 0
        self.mask = m
        self.shape = shape
        self.index = np.flatnonzero(m)
        self.count = int(self.index.size)
        if self.count == 0:
            raise ValueError(f"{name}: the mask selects no pixels")
        self._index_t: dict = {}
        self._runs = None

    def bbox(self, margin: int = 0) -> tuple[slice, slice]:
        """Row and column slices of the mask's bounding box, grown by ``margin`` pixels (clipped)."""
        rows = np.flatnonzero(self.mask.any(1))
        cols = np.flatnonzero(self.mask.any(0))
        H, W = self.shape
        return (slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, H)),
                slice(max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, W)))

    def gather(self, a, axis: int):
        """``a`` with its ``(H, W)`` axes at ``axis, axis + 1`` replaced by ``(1, M)``: the mask's
        pixels in row-major order. numpy in, numpy out (one ``take``); a tensor stays a tensor."""
        shape = tuple(a.shape)
        ax = axis % len(shape)
        if shape[ax:ax + 2] != self.shape:
            raise ValueError(f"PixelMask.gather: axes {ax}, {ax + 1} of shape {shape} must be {self.shape}")
        flat_shape = shape[:ax] + (self.shape[0] * self.shape[1],) + shape[ax + 2:]
        if is_tensor(a):
            idx = self._index_t.get(a.device)
            if idx is None:
                import torch

                idx = self._index_t[a.device] = torch.as_tensor(self.index, device=a.device)
            out = a.reshape(flat_shape).index_select(ax, idx)
        elif len(self.runs) * 4 <= self.count:
            # A compact region (an object's silhouette) is a few runs of pixels per row:
            # copying runs is ~3x faster than a per-pixel take (15.8k-pixel disc: 2 against 6.5 ms).
            a = np.asarray(a)
            out = np.empty(shape[:ax] + (self.count,) + shape[ax + 2:], dtype=a.dtype)
            lead = (slice(None),) * ax
            pos = 0
            for r, c0, c1 in self.runs:
                out[lead + (slice(pos, pos + c1 - c0),)] = a[lead + (r, slice(c0, c1))]
                pos += c1 - c0
        else:
            out = np.take(np.asarray(a).reshape(flat_shape), self.index, axis=ax)
        return out.reshape(shape[:ax] + (1, self.count) + shape[ax + 2:])

    def gather_frames(self, frames):
        """Frames ``(P, H, W, C)`` -> the mask's observations ``(P * C, 1, M)`` (pattern-major,
        channel-minor, the solvers' order), contiguous, in the frames' dtype (no float copy of
        the full frames)."""
        P, H, W, C = tuple(frames.shape)
        g = self.gather(frames, axis=1)[:, 0]  # (P, M, C)
        if is_tensor(g):
            return g.permute(0, 2, 1).reshape(P * C, 1, self.count)
        return np.ascontiguousarray(g.transpose(0, 2, 1)).reshape(P * C, 1, self.count)

    @property
    def runs(self) -> list[tuple[int, int, int]]:
        """``(row, first col, end col)`` of each horizontal run of mask pixels, row-major."""
        if self._runs is None:
            edges = np.diff(np.pad(self.mask.astype(np.int8), ((0, 0), (1, 1))), axis=1)
            r0, c0 = np.nonzero(edges == 1)
            _, c1 = np.nonzero(edges == -1)  # same row-major order: one end per start
            self._runs = list(zip(r0.tolist(), c0.tolist(), c1.tolist()))
        return self._runs

    def scatter_array(self, values, fill, axis: int = 0) -> np.ndarray:
        """Put per-pixel ``values`` (``(..., M, ...)`` with the pixel axis at ``axis``, or
        ``(..., 1, M, ...)``) into a full frame ``(..., H, W, ...)`` filled with ``fill``."""
        v = np.asarray(values)
        if v.ndim > axis + 1 and v.shape[axis] == 1 and v.shape[axis + 1] == self.count:
            v = v.reshape(v.shape[:axis] + (self.count,) + v.shape[axis + 2:])
        H, W = self.shape
        fill = np.asarray(fill, dtype=v.dtype)
        if not fill.any():  # zero pages come free from the OS: no pass over the frame
            out = np.zeros(v.shape[:axis] + (H * W,) + v.shape[axis + 1:], dtype=v.dtype)
        else:
            out = np.empty(v.shape[:axis] + (H * W,) + v.shape[axis + 1:], dtype=v.dtype)
            out[...] = fill.reshape((1,) * (axis + 1) + fill.shape)
        index = (slice(None),) * axis + (self.index,)
        out[index] = v
        return out.reshape(v.shape[:axis] + (H, W) + v.shape[axis + 1:])

    def scatter(self, res: NormalResult) -> NormalResult:
        """A solver's result on the gathered pixels (arrays ``(1, M, ...)``) as a full-frame
        :class:`NormalResult`; pixels outside the mask are invalid (see the module docstring)."""
        flat = np.zeros(3, dtype=res.normals.dtype)
        flat[2] = 1.0
        return NormalResult(
            normals=self.scatter_array(res.normals, flat),
            albedo=self.scatter_array(res.albedo, np.zeros(res.albedo.shape[-1], res.albedo.dtype)),
            residual=self.scatter_array(res.residual, 0),
            condition=self.scatter_array(res.condition, COND_CAP),
            mask=self.scatter_array(res.mask, False),
            count=self.scatter_array(res.count, 0),
            meta=dict(res.meta, masked_pixels=self.count),
            confidence=None if res.confidence is None else self.scatter_array(res.confidence, 0),
        )

    def restrict(self, res: NormalResult) -> NormalResult:
        """A full-frame result with every pixel outside the mask marked invalid (for solvers
        that must see the whole frame, like a lookup table with a per-pixel reference)."""
        if tuple(res.mask.shape) != self.shape:
            raise ValueError(f"PixelMask.restrict: result is {tuple(res.mask.shape)}, mask is {self.shape}")
        names = ("normals", "albedo", "residual", "condition", "mask", "count") + \
            (("confidence",) if res.confidence is not None else ())
        take = {k: self.gather(getattr(res, k)[None], axis=1)[0] for k in names}
        return self.scatter(NormalResult(**take, meta=res.meta))


def masked_solve(solve, observations, mask, *, lights=None, name: str = "solver") -> NormalResult:
    """Run ``solve`` on the masked pixels only and scatter its result into the full frame.

    Parameters
    ----------
    solve : callable
        ``solve(observations (N, 1, M), lights) -> NormalResult`` on ``M`` gathered pixels.
    observations : ndarray or tensor, shape (N, H, W)
    mask : array_like, shape (H, W)
    lights : ndarray, shape (N, 3) or (N, H, W, 3), optional
        Shared lights pass through; per-pixel lights are gathered with the observations.
    name : str
        For error messages.

    Examples
    --------
    >>> from pipeline.normals import solve_farfield
    >>> L = np.array([[0, 0, 1.0], [0.5, 0, 1], [0, 0.5, 1]])
    >>> I = np.broadcast_to((L @ [0, 0, 1.0])[:, None, None], (3, 2, 2))
    >>> m = np.array([[True, False], [False, False]])
    >>> res = masked_solve(lambda o, l: solve_farfield(o, l), I, m, lights=L)
    >>> res.mask.tolist(), res.count.tolist()
    ([[True, False], [False, False]], [[3, 0], [0, 0]])
    """
    shape = tuple(observations.shape)
    if len(shape) != 3:
        raise ValueError(f"{name}: observations must have shape (N_obs, H, W), got {shape}")
    pm = PixelMask(mask, shape[1:], name)
    obs = pm.gather(observations, axis=1)
    L = lights
    if lights is not None and len(lights.shape) == 4:
        if tuple(lights.shape[1:3]) != pm.shape:
            raise ValueError(f"{name}: lights must have shape ({shape[0]}, {pm.shape[0]}, {pm.shape[1]}, 3), "
                             f"got {tuple(lights.shape)}")
        L = pm.gather(lights, axis=1)
    return pm.scatter(solve(obs, L))


def solves_in_mask(func):
    """Decorator: give a solver ``func(observations (N, H, W), lights, **options)`` a ``mask=``
    keyword that runs it through :func:`masked_solve` (``mask=None``: the whole frame)."""

    @functools.wraps(func)
    def wrapper(observations, lights, *args, mask=None, **kwargs):
        if mask is None:
            return func(observations, lights, *args, **kwargs)
        return masked_solve(lambda obs, L: func(obs, L, *args, **kwargs), observations, mask, lights=lights,
                            name=func.__name__)

    return wrapper


def pixel_batches(M: int, N: int, elements: int = BATCH_ELEMENTS) -> list[tuple[int, int]]:
    """Pixel ranges ``[(a, b), ...]`` covering ``M`` pixels, each of at most ``elements / N``
    pixels, so that an ``(N, batch)`` temporary stays within ``elements``.

    Examples
    --------
    >>> pixel_batches(10, 4, elements=16)
    [(0, 3), (3, 6), (6, 10)]
    """
    per = max(1, int(elements) // max(int(N), 1))
    if M <= per:
        return [(0, M)]
    n = -(-M // per)
    edges = [M * i // n for i in range(n + 1)]  # balanced: no small tail batch
    return list(zip(edges[:-1], edges[1:]))
