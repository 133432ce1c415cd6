"""Binning rays onto a pixel grid: the irradiance image and the vector irradiance field V.

A ray of power ``w`` (after Fresnel losses) crossing the plane of the gel at pixel ``x``
adds ``w / A`` to the flat-gel irradiance ``E(x)`` (``A`` the pixel area) and
``w l / (A |l . z|)`` to the vector irradiance ``V(x)``, ``l = -d`` the unit vector back
toward where the ray came from. The ``1 / |l . z|`` turns the flat pixel into the area
perpendicular to the ray, so that ``n . V`` is the irradiance of a surface element of any
normal ``n`` (for ``n = z`` it is ``E``) and a bare point source gives ``V = I l / r^2``
exactly as the closed form in :mod:`sim.point_source`.

Multi-source by hit rotation: LED ``i`` of a symmetric ring is LED 0 rotated about ``z`` by
``phi_i``; so are its rays. Binning LED 0's hits rotated by ``phi_i`` gives LED ``i``'s image
exactly (no interpolation); its V is LED 0's accumulated vectors rotated by ``phi_i``,
applied once per image rather than once per ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from sim.optics import instrument
from sim.optics.plane import plane_hit

__all__ = ["PixelGrid", "BinLayout", "FieldAccumulator", "bin_passes"]

SPARE = 16  # bins past the last pixel that take off-grid hits (see bin_passes)


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
    """What a :class:`FieldAccumulator` bins, as plain hashable values (a compiled tracer keys on it).

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


def bin_passes(layout: BinLayout, o, d, w, compact: bool = True):
    """``[(idx, vals), ...]``, one per pass of ``layout`` (heights outer, angles inner), and the
    (N, C) contributions ``vals = [E, V_x, V_y]`` (or ``[E]``) of each ray.

    With ``compact``, ``idx`` is the ray's pixel in the pass (int64; ``H*W`` off the grid).
    Without, it is where the row's first channel goes in a :class:`FieldAccumulator`'s flat
    storage (int32 while that holds less than 2^31 values: half the memory traffic), which is
    all a scatter then has to do.

    ``V_z`` is not binned: a ray's ``w l_z / (A |l_z|)`` is ``-w / A`` (``l_z < 0`` toward
    the LEDs), so ``V_z = -E`` exactly. ``compact`` keeps only the rays that can land on the
    grid under some rotation (eager: fewer rows to scatter); without it every ray keeps its
    row and the others go to the spare bins ``H*W ...`` with zero contributions (elementwise
    only: what ``torch.compile`` fuses).
    """
    grid = layout.grid
    H, W = grid.shape
    cy, cx = grid.centre
    py, px = grid.pitch
    inv_a = 1.0 / grid.area
    # A hit lands on the grid under some rotation only within the grid's circumradius.
    r2 = ((H / 2.0 + 1.0) * py) ** 2 + ((W / 2.0 + 1.0) * px) ** 2
    C = 3 if layout.vector else 1
    out = []
    for h in layout.heights:
        x, y, _, ok = plane_hit(o, d, grid.z - h)
        ok = ok & (w > 0) & (x * x + y * y <= r2)
        if compact:
            x, y, wv = x[ok], y[ok], w[ok]
            dd = tuple(c[ok] for c in d)
        else:
            wv = torch.where(ok, w, torch.zeros_like(w))
            dd = (d[0], d[1], torch.where(ok, d[2], torch.ones_like(d[2])))
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
            if compact:
                idx = torch.where(inb, row * W + col, torch.full_like(row, H * W)).to(torch.int64)
            else:
                # Off-grid rows go round-robin to SPARE bins: all into one, each scatter would wait
                # on the previous one's store (measured 2.5x slower).
                it = torch.int32 if layout.passes * (H * W + SPARE) * C < 2 ** 31 else torch.int64
                lane = torch.arange(len(row), device=row.device, dtype=it) % SPARE
                pix = torch.where(inb & ok, row * W + col, torch.full_like(row, -1.0)).to(it)  # in range: no UB
                idx = torch.where(pix >= 0, pix, H * W + lane)
                idx = (idx + len(out) * (H * W + SPARE)) * C
            out.append((idx, vals))
    return out


def _scatter_rows(flat, offset, vals):
    """``flat[offset[n] + c] += vals[n, c]``: ``index_add_`` of rows into a flat accumulator."""
    # (N, C) indices, not flattened: a row loop with the channels inner (flat: 25 % slower).
    i = offset.to(torch.int64)[:, None] + torch.arange(vals.shape[1], device=offset.device)
    flat.index_put_((i,), vals, accumulate=True)


_SCATTER = []


def _compiled_scatter():
    """:func:`_scatter_rows` through ``torch.compile``: one scalar loop, single-threaded (a parallel
    scatter needs atomic adds: measured 7x slower on two threads)."""
    if not _SCATTER:
        # Scalar code: vectorized, inductor loads each 3-channel row as a masked 16-lane vector
        # through a stack buffer (measured 3x slower). No bounds check per value (20 % of the
        # loop): bin_passes makes every offset in range (a pixel only where 0 <= col < W and
        # 0 <= row < H, NaN and inf failing those tests; a spare bin otherwise).
        f = torch.compile(_scatter_rows, dynamic=False,
                          options={"cpp.threads": 1, "cpp.simdlen": 1, "assert_indirect_indexing": False})

        def run(flat, offset, vals):
            for x in (flat, offset, vals):
                torch._dynamo.mark_dynamic(x, 0)
            return f(flat, offset, vals)

        _SCATTER.append(run)
    return _SCATTER[0]


class FieldAccumulator:
    """Accumulates E and V of rays over chunks for several rotations and gel heights.

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
        # On a square grid centred on the axis a quarter turn permutes the pixels exactly, so
        # angles a and a + 90 deg share one binning pass (rot90 of the image): 24 LEDs cost 6.
        self.quarter = {}
        self.binned = list(range(len(self.angles)))
        if H == W and grid.pitch[0] == grid.pitch[1]:
            self.binned = []
            for i, a in enumerate(self.angles):
                for j in self.binned:
                    k = (a - self.angles[j]) / (math.pi / 2)
                    if abs(k - round(k)) < 1e-9:
                        self.quarter[i] = (j, int(round(k)) % 4)
                        break
                else:
                    self.binned.append(i)
        c = 3 if vector else 1
        # (height, binned angle, pixel, [E, V_x, V_y]): a pixel's channels share a cache line
        # (channel-major scatters measured twice as slow); the quarter turns are made by images().
        # Spare bins from index H*W take the off-grid hits, so no per-angle masking is needed.
        self.acc = torch.zeros(len(self.heights), len(self.binned), H * W + SPARE, c, device=self.device,
                               dtype=dtype)

    @property
    def layout(self) -> BinLayout:
        return BinLayout(self.grid, tuple(self.heights), tuple(self.angles[i] for i in self.binned), self.vector)

    def add(self, o, d, w) -> None:
        """Bin rays leaving the optics: origins ``o``, unit directions ``d``, powers ``w`` (N,)."""
        self.add_passes(bin_passes(self.layout, o, d, w, compact=True))

    def add_passes(self, passes, compiled: bool = False) -> None:
        """Scatter :func:`bin_passes` output (of this accumulator's :attr:`layout`) into the images:
        ``compact`` passes by ``index_add_``, the others (``compiled``) by one ``torch.compile``d
        loop (measured 2 ns per ray and pass on the default scene; the fused tracer uses it).
        """
        if compiled:
            flat = self.acc.view(-1)
            for offset, vals in passes:
                _compiled_scatter()(flat, offset, vals)
            return
        B = self.acc.shape[1]
        for k, (idx, vals) in enumerate(passes):
            self.acc[k // B, k % B].index_add_(0, idx, vals)

    def _per_angle(self):
        """The accumulated (D, K, H, W, C) images of every angle (quarter turns by exact ``rot90``)."""
        H, W = self.grid.shape
        D = len(self.heights)
        binned = self.acc[:, :, :H * W].reshape(D, len(self.binned), H, W, -1)
        slot = {ai: b for b, ai in enumerate(self.binned)}
        out = []
        for i in range(len(self.angles)):
            if i in slot:
                out.append(binned[:, slot[i]])
            else:
                j, k = self.quarter[i]
                # A turn by +90 deg about z maps (x, y) -> (-y, x); x runs along columns and y
                # along rows, so that is rot90 from the column axis toward the row axis.
                out.append(torch.rot90(binned[:, slot[j]], k, dims=(2, 1)))
        return torch.stack(out, 1)

    def images(self):
        """``E`` of shape (D, K, H, W) and ``V`` of shape (D, K, H, W, 3), optical frame, rotated per angle."""
        img = self._per_angle()
        E = img[..., 0]
        if not self.vector:
            return E, None
        vx, vy = img[..., 1], img[..., 2]
        # Rotate each angle's vectors with its image (the binned ones are LED 0's rays rotated).
        ca = torch.tensor([math.cos(a) for a in self.angles], dtype=E.dtype, device=E.device)[None, :, None, None]
        sa = torch.tensor([math.sin(a) for a in self.angles], dtype=E.dtype, device=E.device)[None, :, None, None]
        V = torch.stack([ca * vx - sa * vy, sa * vx + ca * vy, -E], dim=-1)
        return E, V

    @property
    def on_grid(self):
        """Power (W per W emitted) landing on the grid per (height, angle), shape (D, K)."""
        H, W = self.grid.shape
        per_slot = self.acc[:, :, :H * W, 0].double().sum(-1) * self.grid.area  # a quarter turn keeps the sum
        slot = {ai: b for b, ai in enumerate(self.binned)}
        cols = [slot[i] if i in slot else slot[self.quarter[i][0]] for i in range(len(self.angles))]
        return per_slot[:, cols].cpu()
