"""Binning rays onto a pixel grid with torch: the reference tracer's accumulator.

The conventions (what a ray adds to ``E`` and ``V``, hit rotation, the quarter-turn shortcut)
are :mod:`sim.optics.grid`'s, which also assembles the images; this module bins torch rays
(:func:`bin_passes`) into a :class:`FieldAccumulator`. The compiled kernel bins into
:class:`sim.optics.grid.ImageBins` instead.
"""

from __future__ import annotations

import math

import torch

from sim.optics import instrument
from sim.optics.grid import BinLayout, PixelGrid, assemble_images, on_grid_power, quarter_plan
from sim.optics.plane import plane_hit

__all__ = ["PixelGrid", "BinLayout", "FieldAccumulator", "bin_passes"]


def bin_passes(layout: BinLayout, o, d, w):
    """``[(idx, vals), ...]``, one per pass of ``layout`` (heights outer, angles inner): each ray's
    pixel in the pass (int64; ``H*W`` off the grid) and the (N, C) contributions
    ``vals = [E, V_x, V_y]`` (or ``[E]``) of the rays that can land on the grid under some rotation.

    ``V_z`` is not binned: a ray's ``w l_z / (A |l_z|)`` is ``-w / A`` (``l_z < 0`` toward the
    LEDs), so ``V_z = -E`` exactly.
    """
    grid = layout.grid
    H, W = grid.shape
    cy, cx = grid.centre
    py, px = grid.pitch
    inv_a = 1.0 / grid.area
    out = []
    for h in layout.heights:
        x, y, _, ok = plane_hit(o, d, grid.z - h)
        # A hit lands on the grid under some rotation only within the grid's reach.
        ok = ok & (w > 0) & (x * x + y * y <= grid.reach2)
        x, y, wv = x[ok], y[ok], w[ok]
        dd = tuple(c[ok] for c in d)
        e = wv * inv_a
        if layout.vector:
            # V contribution w l / (A |l_z|) with l = -d and |l_z| = d_z > 0 here.
            s = -e / dd[2]
            vals = torch.stack([e, s * dd[0], s * dd[1]], dim=1)
        else:
            vals = e[:, None]
        for a in layout.angles:
            if a == 0.0:
                xr, yr = x, y
            else:
                ca, sa = math.cos(a), math.sin(a)
                xr, yr = ca * x - sa * y, sa * x + ca * y
            col = torch.floor(xr * (1.0 / px) + (cx + 0.5))
            row = torch.floor(yr * (1.0 / py) + (cy + 0.5))
            inb = (col >= 0) & (col < W) & (row >= 0) & (row < H)
            out.append((torch.where(inb, row * W + col, torch.full_like(row, H * W)).to(torch.int64), vals))
    return out


class FieldAccumulator:
    """Accumulates E and V of torch rays over chunks for several rotations and gel heights.

    Parameters
    ----------
    grid : PixelGrid
        The pixel grid at gel height 0.
    angles : sequence of float
        Rotations about ``z`` (radians) applied to the hits: one image per angle.
    heights : sequence of float
        Gel heights (mm toward the camera, i.e. optical ``-z``) at which to bin.
    vector : bool
        Also accumulate V (the irradiance image alone is cheaper).
    """

    def __init__(self, grid: PixelGrid, angles=(0.0,), heights=(0.0,), vector: bool = True, device="cpu",
                 dtype=torch.float32):
        self.grid = grid
        self.angles = [float(a) for a in angles]
        self.heights = [float(h) for h in heights]
        if len(self.heights) > 1 or self.heights[0] != 0.0:
            instrument.count("depth_field")
        self.vector = vector
        self.device = torch.device(device)
        self.dtype = dtype
        H, W = grid.shape
        # Angles a quarter turn apart share one binning pass (rot90 of the image): 24 LEDs cost 6.
        self.binned, self.quarter = quarter_plan(grid, self.angles)
        # (height, binned angle, pixel, [E, V_x, V_y]), plus one bin past the last pixel for the
        # off-grid hits (no per-angle masking needed); the quarter turns are made by images().
        self.acc = torch.zeros(len(self.heights), len(self.binned), H * W + 1, 3 if vector else 1,
                               device=self.device, dtype=dtype)

    @property
    def layout(self) -> BinLayout:
        return BinLayout(self.grid, tuple(self.heights), tuple(self.angles[i] for i in self.binned), self.vector)

    def add(self, o, d, w) -> None:
        """Bin rays leaving the optics: origins ``o``, unit directions ``d``, powers ``w`` (N,)."""
        B = self.acc.shape[1]
        for k, (idx, vals) in enumerate(bin_passes(self.layout, o, d, w)):
            self.acc[k // B, k % B].index_add_(0, idx, vals)

    def add_binned(self, binned) -> None:
        """Add images binned elsewhere (the compiled kernel's, numpy (D, B, H * W, C) of this :attr:`layout`)."""
        H, W = self.grid.shape
        self.acc[:, :, :H * W] += torch.as_tensor(binned, dtype=self.dtype).to(self.device)

    def _binned(self):
        H, W = self.grid.shape
        return self.acc[:, :, :H * W].cpu().numpy()

    def images(self):
        """``E`` of shape (D, K, H, W) and ``V`` of shape (D, K, H, W, 3), optical frame, rotated per angle."""
        E, V = assemble_images(self._binned(), self.grid, self.angles, self.binned, self.quarter, self.vector)
        to = lambda a: None if a is None else torch.from_numpy(a.copy()).to(self.device)  # noqa: E731
        return to(E), to(V)

    @property
    def on_grid(self):
        """Power (W per W emitted) landing on the grid per (height, angle), shape (D, K)."""
        return torch.from_numpy(on_grid_power(self._binned()[..., 0], self.grid, len(self.angles), self.binned,
                                              self.quarter))
