"""Lookup-table normals from a single RGB frame (GelSight style), via the calibration's table.

The table itself (colour -> surface gradient, built from sphere presses) belongs to the
calibration stage: any object with ``lookup(images (N, H, W, 3)) -> (gradients (N, H, W, 2),
valid (N, H, W))`` works, gradients being ``(dh/dx, dh/dy)`` in the reconstruction frame.
A table has no light matrix, so the condition number reads 1 and the residual 0; albedo is
not estimated by a lookup and is reported as 1 at valid pixels.
"""

from __future__ import annotations

import numpy as np

from pipeline.base.frames import gradients_to_normals
from pipeline.normals.result import NormalResult

__all__ = ["LUTSolver", "solve_lut"]


class LUTSolver:
    """Normals by looking up each pixel's colour in a calibrated table.

    Parameters
    ----------
    table : object
        Has ``lookup(images)`` as described in the module docstring (the calibration stage's
        ``LookupTable``).
    max_slope : float
        Gradients are clipped to this magnitude (mm/mm) so a wild table entry stays finite.

    Examples
    --------
    A table that knows one colour: red means a slope of 0.75 along +x.

    >>> class Red:
    ...     def lookup(self, images):
    ...         red = images[..., 0] > images[..., 1]
    ...         g = np.zeros(images.shape[:-1] + (2,)); g[..., 0] = np.where(red, 0.75, 0.0)
    ...         return g, np.ones(images.shape[:-1], bool)
    >>> img = np.zeros((1, 2, 3)); img[0, 0] = (1, 0, 0)
    >>> res = LUTSolver(Red()).solve(img)
    >>> np.round(res.normals[0].astype(float), 2).tolist()
    [[-0.6, 0.0, 0.8], [0.0, 0.0, 1.0]]
    """

    def __init__(self, table, *, max_slope: float = 20.0):
        if not callable(getattr(table, "lookup", None)):
            raise ValueError(f"LUTSolver: table must have a lookup(images) method, got {type(table).__name__}")
        self.table = table
        self.max_slope = float(max_slope)

    def solve(self, image, mask=None) -> NormalResult:
        """Normals of one RGB frame ``(H, W, 3)``; with ``mask (H, W)`` the pixels outside it come
        back invalid (the table sees the whole frame: its reference is per pixel)."""
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[-1] != 3:
            raise ValueError(f"LUTSolver.solve: image must have shape (H, W, 3), got {img.shape}")
        if mask is not None:
            from pipeline.normals.masking import PixelMask

            return PixelMask(mask, img.shape[:2], "LUTSolver.solve").restrict(self.solve(img))
        H, W = img.shape[:2]
        finite = np.isfinite(img).all(-1) if img.dtype.kind == "f" else np.ones((H, W), bool)
        clean = np.where(finite[..., None], img, 0) if img.dtype.kind == "f" else img
        grads, valid = self.table.lookup(clean[None])
        grads = np.asarray(grads, dtype=np.float64)
        valid = np.asarray(valid, dtype=bool)
        if grads.shape != (1, H, W, 2) or valid.shape != (1, H, W):
            raise ValueError(f"LUTSolver: table.lookup must return gradients (1, {H}, {W}, 2) and valid "
                             f"(1, {H}, {W}), got {grads.shape} and {valid.shape}")
        g = grads[0]
        ok = valid[0] & finite & np.isfinite(g).all(-1)
        g = np.where(ok[..., None], g, 0.0)
        mag = np.linalg.norm(g, axis=-1, keepdims=True)
        g = np.where(mag > self.max_slope, g * (self.max_slope / np.maximum(mag, 1e-300)), g)
        n = gradients_to_normals(g[..., 0], g[..., 1]).astype(np.float32)
        return NormalResult(
            normals=n,
            albedo=ok[..., None].astype(np.float32),
            residual=np.zeros((H, W), np.float32),
            condition=np.ones((H, W), np.float32),
            mask=ok,
            count=np.where(ok, 3, 0).astype(np.int32),
            meta={"solver": "lut", "max_slope": self.max_slope},
        )


def solve_lut(image, table, mask=None, **kwargs) -> NormalResult:
    """One-shot :class:`LUTSolver` on an RGB frame ``(H, W, 3)`` (optional ``mask (H, W)``)."""
    return LUTSolver(table, **kwargs).solve(image, mask=mask)
