"""Solve only where asked: gather a mask's pixels once, solve them in batches, scatter back.

A photometric-stereo object (a DiLiGenT capture: 15.8k object pixels in a 612 x 512 frame)
or a user's region of interest covers a small part of the image. Every solver takes
``mask=`` and goes through :class:`PixelMask`: the masked pixels of the observations (and of
per-pixel lights) are gathered into a ``(N, 1, M)`` "image" of ``M`` pixels, the solver runs
on that, and :meth:`PixelMask.scatter` puts the result back into the full frame, with every
pixel outside the mask marked invalid: ``mask`` False, ``count`` 0 (no observation used, the
confidence), flat normal ``(0, 0, 1)``, albedo and residual 0, condition at the cap. No NaN.

This module is the one place that does it, so every solver's masked result has the same
layout (tests compare each solver's masked result with its full-frame one on the mask). The
gather and the scatter of plain arrays are :class:`pipeline.base.pixel_mask.PixelMask`'s (the
depth integrators' ``region=`` uses that too); this :class:`PixelMask` adds the result's scatter.
:func:`pixel_batches` splits a long pixel axis into batches that bound a solver's
temporaries (``N x batch`` floats each).
"""

from __future__ import annotations

import functools

import numpy as np

from pipeline.base import pixel_mask
from pipeline.normals.result import COND_CAP, NormalResult

__all__ = ["PixelMask", "masked_solve", "solves_in_mask", "pixel_batches", "BATCH_ELEMENTS"]

#: Elements (observations x pixels) of one batch: 8 M floats = 32 MB per float32 temporary.
BATCH_ELEMENTS = 1 << 23


class PixelMask(pixel_mask.PixelMask):
    """:class:`pipeline.base.pixel_mask.PixelMask` (the mask's pixels, gathered from any array)
    that also scatters a solver's :class:`NormalResult` back into the full frame.

    Examples
    --------
    >>> pm = PixelMask([[True, False], [False, True]], (2, 2), "demo")
    >>> pm.count, pm.gather(np.arange(8).reshape(2, 2, 2), axis=1).tolist()
    (2, [[[0, 3]], [[4, 7]]])
    """

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
