"""Pixel grids, binning layouts and the images they accumulate (numpy; no torch).

A ray of power ``w`` (after Fresnel losses) crossing the plane of the gel at pixel ``x``
adds ``w / A`` to the flat-gel irradiance ``E(x)`` (``A`` the pixel area) and
``w l / (A |l . z|)`` to the vector irradiance ``V(x)``, ``l = -d`` the unit vector back
toward where the ray came from. The ``1 / |l . z|`` turns the flat pixel into the area
perpendicular to the ray, so that ``n . V`` is the irradiance of a surface element of any
normal ``n`` (for ``n = z`` it is ``E``) and a bare point source gives ``V = I l / r^2``
exactly as the closed form in :mod:`sim.point_source`. On the flat gel ``V_z = -E`` exactly,
so only ``E``, ``V_x`` and ``V_y`` are binned.

Multi-source by hit rotation: LED ``i`` of a symmetric ring is LED 0 rotated about ``z`` by
``phi_i``; so are its rays. Binning LED 0's hits rotated by ``phi_i`` gives LED ``i``'s image
exactly (no interpolation); its V is LED 0's accumulated vectors rotated by ``phi_i``,
applied once per image rather than once per ray. On a square grid centred on the axis a
quarter turn permutes the pixels exactly, so angles a quarter turn apart share one binning
pass (:func:`quarter_plan`): 24 LEDs cost 6 passes.

This module owns those conventions for both tracers: :class:`ImageBins` holds the compiled
kernel's images (:mod:`sim.optics.engine`), :class:`sim.optics.binning.FieldAccumulator` the
torch reference's, and both assemble their images with :func:`assemble_images`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["PixelGrid", "BinLayout", "quarter_plan", "assemble_images", "on_grid_power", "ImageBins"]


@dataclass(frozen=True)
class PixelGrid:
    """A pixel grid on a plane ``z`` of the optical frame, centred on the axis (:mod:`pipeline.base.frames`).

    ``pitch = (mm per row, mm per col)``. Pixel ``(row, col)`` has its centre at
    ``x = (col - cx) * pitch[1]``, ``y = (row - cy) * pitch[0]``.

    Examples
    --------
    >>> g = PixelGrid((3, 4), (0.5, 0.5), 10.0)
    >>> g.area, g.centre
    (0.25, (1.0, 1.5))
    """

    shape: tuple[int, int]
    pitch: tuple[float, float]
    z: float

    @property
    def area(self) -> float:
        return self.pitch[0] * self.pitch[1]

    @property
    def centre(self) -> tuple[float, float]:
        return (self.shape[0] - 1) / 2.0, (self.shape[1] - 1) / 2.0

    @property
    def reach2(self) -> float:
        """Squared radius beyond which no hit lands on the grid under any rotation (with a pixel's margin)."""
        H, W = self.shape
        return ((H / 2.0 + 1.0) * self.pitch[0]) ** 2 + ((W / 2.0 + 1.0) * self.pitch[1]) ** 2

    @classmethod
    def from_plane(cls, plane) -> "PixelGrid":
        """The grid of a :class:`sim.scene.ImagingPlane`."""
        return cls(tuple(plane.resolution), tuple(plane.mm_per_px), float(plane.z))

    @classmethod
    def camera(cls, shape, mm_per_px: float, z: float) -> "PixelGrid":
        """The camera's orthographic pixel grid ``(H, W)`` at ``mm_per_px`` on the gel plane ``z``."""
        return cls((int(shape[0]), int(shape[1])), (float(mm_per_px), float(mm_per_px)), float(z))


@dataclass(frozen=True)
class BinLayout:
    """What an accumulator bins, as plain hashable values.

    ``angles`` are the rotations that get a binning pass of their own (quarter turns of
    them are filled by ``rot90``); one pass per (height, angle), heights outer.
    """

    grid: PixelGrid
    heights: tuple
    angles: tuple
    vector: bool

    @property
    def passes(self) -> int:
        return len(self.heights) * len(self.angles)

    @property
    def channels(self) -> int:
        return 3 if self.vector else 1


def quarter_plan(grid: PixelGrid, angles):
    """``(binned, quarter)``: the indices of ``angles`` that need a binning pass, and for every other
    index ``i`` the pair ``(j, k)``: its image is binned angle ``j``'s turned by ``k`` quarter turns.

    Examples
    --------
    >>> quarter_plan(PixelGrid((4, 4), (1.0, 1.0), 0.0), [0.0, math.pi / 2, 0.3])
    ([0, 2], {1: (0, 1)})
    """
    angles = [float(a) for a in angles]
    H, W = grid.shape
    if not (H == W and grid.pitch[0] == grid.pitch[1]):
        return list(range(len(angles))), {}
    binned, quarter = [], {}
    for i, a in enumerate(angles):
        for j in binned:
            k = (a - angles[j]) / (math.pi / 2)
            if abs(k - round(k)) < 1e-9:
                quarter[i] = (j, int(round(k)) % 4)
                break
        else:
            binned.append(i)
    return binned, quarter


def assemble_images(binned, grid: PixelGrid, angles, binned_idx, quarter, vector: bool):
    """Images of every angle from the binned passes.

    Parameters
    ----------
    binned : ndarray, shape (D, B, H * W, C)
        Accumulated ``[E, V_x, V_y]`` (or ``[E]``) of each height and binned angle, LED 0's frame.
    angles, binned_idx, quarter :
        The accumulator's angles and :func:`quarter_plan` of them.

    Returns
    -------
    E : ndarray (D, K, H, W) and V : ndarray (D, K, H, W, 3) or None, optical frame.
    """
    H, W = grid.shape
    D = binned.shape[0]
    img = binned.reshape(D, len(binned_idx), H, W, -1)
    slot = {ai: b for b, ai in enumerate(binned_idx)}
    out = []
    for i in range(len(angles)):
        if i in slot:
            out.append(img[:, slot[i]])
        else:
            j, k = quarter[i]
            # A turn by +90 deg about z maps (x, y) -> (-y, x); x runs along columns and y
            # along rows, so that is rot90 from the column axis toward the row axis.
            out.append(np.rot90(img[:, slot[j]], k, axes=(2, 1)))
    per = np.stack(out, 1)
    E = np.ascontiguousarray(per[..., 0])
    if not vector:
        return E, None
    vx, vy = per[..., 1], per[..., 2]
    # Rotate each angle's vectors with its image (the binned ones are LED 0's rays rotated).
    ca = np.array([math.cos(a) for a in angles], dtype=E.dtype)[None, :, None, None]
    sa = np.array([math.sin(a) for a in angles], dtype=E.dtype)[None, :, None, None]
    return E, np.stack([ca * vx - sa * vy, sa * vx + ca * vy, -E], axis=-1)


def on_grid_power(binned_e, grid: PixelGrid, n_angles: int, binned_idx, quarter) -> np.ndarray:
    """Power (W per W emitted) on the grid per (height, angle), shape (D, K), from binned ``E`` (D, B, H * W)."""
    per_slot = binned_e.astype(np.float64).sum(-1) * grid.area  # a quarter turn keeps the sum
    slot = {ai: b for b, ai in enumerate(binned_idx)}
    cols = [slot[i] if i in slot else slot[quarter[i][0]] for i in range(n_angles)]
    return per_slot[:, cols]


class ImageBins:
    """The images of one :class:`BinLayout`, filled by the compiled kernel (numpy, any device's result).

    Parameters mirror :class:`sim.optics.binning.FieldAccumulator`: ``grid``, ``angles``
    (radians, one image each), ``heights`` (mm toward the camera), ``vector`` (also ``V``),
    ``dtype`` (``float32`` or ``float64``).

    Examples
    --------
    >>> b = ImageBins(PixelGrid((4, 4), (1.0, 1.0), 5.0), angles=[0.0, math.pi / 2])
    >>> b.layout.passes, b.acc.shape
    (1, (1, 1, 16, 3))
    """

    def __init__(self, grid: PixelGrid, angles=(0.0,), heights=(0.0,), vector: bool = True, dtype=np.float32):
        self.grid = grid
        self.angles = [float(a) for a in angles]
        self.heights = [float(h) for h in heights]
        self.vector = bool(vector)
        self.binned, self.quarter = quarter_plan(grid, self.angles)
        H, W = grid.shape
        self.acc = np.zeros((len(self.heights), len(self.binned), H * W, 3 if vector else 1), dtype=dtype)

    @property
    def layout(self) -> BinLayout:
        return BinLayout(self.grid, tuple(self.heights), tuple(self.angles[i] for i in self.binned), self.vector)

    def add_binned(self, binned) -> None:
        """Add the kernel's images of this :attr:`layout`, (D, B, H * W, C)."""
        self.acc += binned

    def images(self):
        """``E`` (D, K, H, W) and ``V`` (D, K, H, W, 3) or None, optical frame, one image per angle."""
        return assemble_images(self.acc, self.grid, self.angles, self.binned, self.quarter, self.vector)

    @property
    def on_grid(self) -> np.ndarray:
        """Power (W per W emitted) landing on the grid per (height, angle), shape (D, K)."""
        return on_grid_power(self.acc[..., 0], self.grid, len(self.angles), self.binned, self.quarter)
