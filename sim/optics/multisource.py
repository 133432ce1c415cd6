"""Every LED of the ring, three ways (paper §IV-B2 and two better ones).

``image``  the paper's: trace LED 0, bin it once, rotate its image by each LED's azimuth with
           a bilinear warp (kornia) and rotate V's vectors; interpolation blurs and loses
           the corners.
``hits``   trace LED 0 once and bin its rays rotated by each LED's azimuth: exact for a
           rotationally symmetric ring and lens (no interpolation), one trace for all LEDs.
``trace``  trace every LED: the reference (and the only choice for a non-symmetric ring).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from sim.optics import engine as _engine
from sim.optics.grid import ImageBins, PixelGrid

__all__ = ["METHODS", "FieldResult", "led_azimuths", "trace_all", "rotate_images"]

METHODS = ("hits", "image", "trace")


@dataclass
class FieldResult:
    """Per-LED images on one pixel grid.

    Attributes
    ----------
    E : ndarray, shape (D, L, H, W)
        Flat-gel irradiance per LED (W/mm^2 per W emitted) at each of the D gel heights
        (float32, or float64 for a float64 trace).
    V : ndarray, shape (D, L, H, W, 3) or None
        Vector irradiance, **optical** frame (convert with :func:`pipeline.base.frames.optical_to_recon`).
    grid : PixelGrid
    heights : tuple of float
    traces : list of SourceTrace
    seconds : float
    fraction_on_grid : ndarray, shape (L,)
        Fraction of each LED's power landing on the grid at height 0.
    """

    E: np.ndarray
    V: np.ndarray | None
    grid: PixelGrid
    heights: tuple
    traces: list
    seconds: float
    fraction_on_grid: np.ndarray = field(default_factory=lambda: np.zeros(0))


def led_azimuths(scene) -> np.ndarray:
    """Azimuth (rad) of each LED of the ring, shape (L,).

    Examples
    --------
    >>> from sim.scene import load_scene
    >>> np.round(np.degrees(led_azimuths(load_scene("default"))[:3]), 6).tolist()
    [0.0, 15.0, 30.0]
    """
    pos, _ = scene.leds.geometry()
    L = scene.leds.count
    return np.radians(scene.leds.phase_deg) + 2.0 * np.pi * np.arange(L) / L if scene.leds.radius > 0 else \
        np.arctan2(pos[:, 1], pos[:, 0])


def trace_all(scene, grid: PixelGrid | None = None, *, method: str = "hits", heights=(0.0,), vector: bool = True,
              rays: int | None = None, sampler: str | None = None, seed: int | None = None, device="cpu",
              dtype=None, chunk: int | None = None, refractive_index: float | None = None, leds=None,
              intersection: str | None = None, engine: str | None = None, threads: int | None = None) -> FieldResult:
    """Images of every LED (or of ``leds``) of ``scene`` on ``grid`` (default: the scene's imaging plane).

    ``engine`` picks the compiled kernel (the default for the robust intersection; torch is
    not imported) or the eager torch reference (:func:`sim.optics.engine.resolve_engine`);
    ``dtype`` is float32 (default) or float64; ``chunk`` (torch engine) bounds the rays per
    chunk; ``threads`` the kernel's CPU threads. The other parameters are
    :func:`sim.optics.tracer.trace_source`'s.

    Examples
    --------
    >>> from sim.scene import load_scene
    >>> s = load_scene("default")
    >>> g = PixelGrid((8, 8), (4.0, 4.0), s.plane.z)
    >>> r = trace_all(s, g, rays=4096)
    >>> r.E.shape, r.V.shape
    ((1, 24, 8, 8), (1, 24, 8, 8, 3))
    """
    if method not in METHODS:
        raise ValueError(f"trace_all: method must be one of {METHODS}, got {method!r}")
    t0 = time.perf_counter()
    grid = grid or PixelGrid.from_plane(scene.plane)
    az = led_azimuths(scene)
    leds = list(range(scene.leds.count)) if leds is None else [int(i) for i in leds]
    kind = _engine.resolve_engine(engine, intersection or scene.trace.intersection, scene)
    ft = _engine.float_dtype(dtype)
    kw = dict(rays=rays, sampler=sampler, seed=seed, device=device, refractive_index=refractive_index)
    if kind == "kernel":
        kw.update(threads=threads)

        def make(angles):
            return ImageBins(grid, angles, heights, vector=vector, dtype=ft)

        def trace(led, accs):
            images, res = _engine.trace_led(scene, [a.layout for a in accs], led=led, dtype=ft, **kw)
            for a, img in zip(accs, images):
                a.add_binned(img)
            return res
    else:
        import torch

        from sim.optics.binning import FieldAccumulator
        from sim.optics.tracer import DEFAULT_CHUNK, trace_source

        tdt = getattr(torch, ft.name)
        kw.update(dtype=tdt, chunk=chunk or DEFAULT_CHUNK, intersection=intersection, engine="torch")

        def make(angles):
            return FieldAccumulator(grid, angles, heights, vector=vector, device=device, dtype=tdt)

        def trace(led, accs):
            return trace_source(scene, accs, led=led, **kw)
    traces = []
    if method == "trace":
        Es, Vs, frac = [], [], []
        for i in leds:
            acc = make((0.0,))
            traces.append(trace(i, [acc]))
            E, V = (_numpy(x) for x in acc.images())
            Es.append(E[:, 0])
            Vs.append(V[:, 0] if vector else None)
            frac.append(float(acc.on_grid[0, 0]))
        E = np.stack(Es, 1)
        V = np.stack(Vs, 1) if vector else None
        fr = np.array(frac)
    else:
        angles = [float(az[i] - az[0]) for i in leds] if method == "hits" else [0.0]
        acc = make(angles)
        traces.append(trace(0, [acc]))
        E, V = (_numpy(x) for x in acc.images())
        fr = np.array(_numpy(acc.on_grid)[0], dtype=np.float64)
        if method == "image":
            E, V = rotate_images(E[:, 0], None if V is None else V[:, 0], [float(az[i] - az[0]) for i in leds])
            fr = np.repeat(fr, len(leds))
    return FieldResult(E=E, V=V, grid=grid, heights=tuple(heights), traces=traces, seconds=time.perf_counter() - t0,
                       fraction_on_grid=fr)


def _numpy(x):
    """A numpy array of a numpy array or a torch tensor on any device (None stays None)."""
    if x is None or isinstance(x, np.ndarray):
        return x
    return x.detach().cpu().numpy()


def rotate_images(E, V, angles):
    """Rotate one LED's images about the optical axis by each angle (the paper's method).

    Parameters
    ----------
    E : ndarray or torch.Tensor, shape (D, H, W)
    V : ndarray or torch.Tensor, shape (D, H, W, 3) or None (optical frame)
    angles : sequence of float (rad)

    Returns
    -------
    E_rot : (D, K, H, W) and V_rot : (D, K, H, W, 3) or None, numpy
    """
    import kornia
    import torch

    E = torch.as_tensor(E)
    V = None if V is None else torch.as_tensor(V)

    D, H, W = E.shape
    K = len(angles)
    chans = E[:, None] if V is None else torch.cat([E[:, None], V.permute(0, 3, 1, 2)], 1)  # (D, C, H, W)
    C = chans.shape[1]
    batch = chans[None].expand(K, D, C, H, W).reshape(K, D * C, H, W)
    # kornia rotates counter-clockwise as displayed with rows downward, i.e. by -angle in a
    # frame whose y grows with the row index (ours, pipeline.base.frames): hence the minus sign.
    deg = torch.tensor([-math.degrees(a) for a in angles], dtype=batch.dtype, device=batch.device)
    out = kornia.geometry.transform.rotate(batch, deg, mode="bilinear", padding_mode="zeros")
    out = out.reshape(K, D, C, H, W).permute(1, 0, 2, 3, 4)  # (D, K, C, H, W)
    E_rot = out[:, :, 0]
    if V is None:
        return _numpy(E_rot), None
    Vr = out[:, :, 1:].permute(0, 1, 3, 4, 2).clone()  # (D, K, H, W, 3)
    for k, a in enumerate(angles):
        c, s = math.cos(a), math.sin(a)
        vx, vy = Vr[:, k, ..., 0].clone(), Vr[:, k, ..., 1].clone()
        Vr[:, k, ..., 0] = c * vx - s * vy
        Vr[:, k, ..., 1] = s * vx + c * vy
    return _numpy(E_rot), _numpy(Vr)
