"""Rendered captures: K contacts x P patterns + reference + dark + exact truth, as schema ``capture``.

This is how the calibration and reconstruction code get synthetic test captures whose truth
is known exactly: the frames come from :class:`sim.render.Renderer`, the truth (height,
normals, albedo) from the same :class:`sim.geometry.HeightField` that was rendered, and the
file layout is the one of ``docs/developing.md`` (written through :func:`pipeline.store.write_record`).

Examples
--------
>>> from sim.render import bare_ring_illumination
>>> model = bare_ring_illumination((30, 40), 0.2)
>>> presses = sphere_presses(model.shape, model.mm_per_px, 2.0, depths=[0.5, 0.8], centers=[(0, 0), (1, -0.5)])
>>> rec = render_capture(model, "monochromatic", presses, noise_dn=1.0, seed=1)
>>> rec.data["frames"].shape, rec.data["frames"].dtype.name, rec.meta["pattern_names"]
((2, 3, 30, 40, 3), 'uint8', ['sector0', 'sector1', 'sector2'])
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from sim.geometry import HeightField, sphere
from sim.illumination_model import IlluminationModel
from sim.modes import LightingMode, load_mode, mode_brightness, mode_drive
from sim.render import RenderSettings, Renderer, auto_exposure

__all__ = ["render_capture", "write_capture", "sphere_presses"]


def sphere_presses(shape: tuple[int, int], mm_per_px: float, radius: float, depths: Sequence[float],
                   centers: Sequence[tuple[float, float]] | None = None) -> list[HeightField]:
    """One :func:`sim.geometry.sphere` press per depth (centres in mm, reconstruction frame).

    Examples
    --------
    >>> [round(float(f.height.max()), 2) for f in sphere_presses((21, 21), 0.1, 2.0, [0.3, 0.6])]
    [0.3, 0.6]
    """
    centers = list(centers) if centers is not None else [(0.0, 0.0)] * len(depths)
    if len(centers) != len(depths):
        raise ValueError(f"sphere_presses: {len(depths)} depths but {len(centers)} centers")
    return [sphere(shape, mm_per_px, radius, float(d), center=tuple(c)) for d, c in zip(depths, centers)]


def render_capture(model: IlluminationModel, mode, contacts: Sequence[HeightField], *, albedo=1.0,
                   settings: RenderSettings | None = None, noise_dn: float = 1.0, bit_depth: int | None = 8,
                   target_dn: float = 200.0, dark: bool = True, seed: int = 0, device="cpu"):
    """Render a capture of ``contacts`` under every pattern of ``mode``.

    Parameters
    ----------
    model : IlluminationModel
        The sensor's illumination (ray-traced, or :func:`sim.render.bare_ring_illumination`).
    mode : str, Path or LightingMode
        Lighting mode (:func:`sim.modes.load_mode`).
    contacts : sequence of HeightField, length K
        One surface per press.
    albedo : float or ndarray (H, W) or (H, W, 3)
    settings : RenderSettings, optional
        Full control of the effects. When omitted: attached shadows, Gaussian read noise of
        ``noise_dn`` DN, saturation and ``bit_depth`` quantization, exposure chosen so the
        brightest flat-gel pixel of any pattern reads ``target_dn``.
    noise_dn, bit_depth, target_dn
        Used only when ``settings`` is omitted.
    dark : bool
        Also render the all-LEDs-off frame.
    seed : int
        Noise seed; frames of press ``k`` use ``seed + k + 1``, the reference ``seed``, the
        dark frame ``seed - 1``.

    Returns
    -------
    pipeline.store.Record
        Schema ``capture``: ``frames`` (K, P, H, W, 3), ``reference`` (P, H, W, 3), ``dark``
        (H, W, 3), ``drive`` (P, L, 3), ``brightness`` (P,), ``truth/height`` (K, H, W),
        ``truth/normals`` (K, H, W, 3), ``truth/albedo`` (H, W, 3); attributes
        ``mm_per_px``, ``pattern_names``, ``mode``, ``exposure``, ``bit_depth``,
        ``source='virtual'`` and ``render_settings``, ``illumination``.
    """
    from pipeline.store import Record

    mode = load_mode(mode) if not isinstance(mode, LightingMode) else mode
    drive, bright = mode_drive(mode), mode_brightness(mode)
    if mode.num_leds != model.num_leds:
        raise ValueError(f"render_capture: mode {mode.name!r} drives {mode.num_leds} LEDs, model has {model.num_leds}")
    contacts = list(contacts)
    h, w = model.shape
    for k, c in enumerate(contacts):
        if not isinstance(c, HeightField) or c.shape != (h, w):
            raise ValueError(f"render_capture: contacts[{k}] must be a HeightField of shape {(h, w)}, "
                             f"got {getattr(c, 'shape', type(c).__name__)}")
    if settings is None:
        mu = auto_exposure(model, drive, bright, target_dn=target_dn)
        settings = RenderSettings(exposure=mu, read_noise=float(noise_dn), saturation=True, bit_depth=bit_depth)
    r = Renderer(model, settings, device=device)
    frames = []
    for k, c in enumerate(contacts):
        r.set_surface(c, albedo)
        frames.append(r.render(drive, bright, seed=seed + k + 1))
    r.set_surface(None, albedo)
    reference = r.render(drive, bright, seed=seed)
    rho = np.asarray(albedo, dtype=np.float32)
    rho = np.broadcast_to(rho[..., None] if rho.ndim == 2 else rho, (h, w, 3)).astype(np.float32)
    data = {
        "frames": np.stack(frames) if frames else np.zeros((0,) + reference.shape, reference.dtype),
        "reference": reference,
        "drive": drive,
        "brightness": bright,
        "truth/height": np.stack([c.height for c in contacts]).astype(np.float32) if contacts
        else np.zeros((0, h, w), np.float32),
        "truth/normals": np.stack([c.normals for c in contacts]).astype(np.float32) if contacts
        else np.zeros((0, h, w, 3), np.float32),
        "truth/albedo": rho,
    }
    if dark:
        data["dark"] = r.render(np.zeros((model.num_leds, 3)), 0.0, seed=seed - 1)
    meta = {
        "mm_per_px": float(model.mm_per_px),
        "pattern_names": mode.pattern_names,
        "mode": mode.name,
        "exposure": float(settings.exposure),
        "bit_depth": int(settings.bit_depth) if settings.bit_depth is not None else 32,
        "source": "virtual",
        "render_settings": settings.to_dict(),
        "illumination": {k: v for k, v in model.meta.items() if isinstance(v, (str, int, float, bool))},
    }
    return Record(schema="capture", data=data, meta=meta)


def write_capture(path, record) -> Path:
    """Write a rendered capture atomically (schema-checked) with :func:`pipeline.store.write_record`."""
    from pipeline.store import write_record

    return write_record(path, record)
