"""Rendered captures: K contacts x P patterns + reference + dark + exact truth, as schema ``capture``.

This is how the calibration and reconstruction code get synthetic test captures whose truth
is known exactly: the frames come from :class:`sim.render.Renderer`, the truth (height,
normals, albedo) from the same :class:`sim.geometry.HeightField` that was rendered, and the
file layout is the one of ``docs/developing.md`` (written by :func:`pipeline.base.capture.write_capture`).

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

from pathlib import Path
from typing import Sequence

import numpy as np

from pipeline.base.modes import LightingMode, load_mode, mode_brightness, mode_drive
from sim.geometry import HeightField, sphere
from sim.illumination_model import IlluminationModel
from sim.render import Renderer, RenderSettings, auto_exposure

__all__ = ["render_capture", "sphere_presses", "press_ring", "save_png", "render_scene_files"]


def press_ring(shape: tuple[int, int], mm_per_px: float, n: int, *, seed: int = 7
               ) -> tuple[list[float], list[tuple[float, float]]]:
    """Depths (mm) and centres (mm, reconstruction frame) of ``n`` calibration presses: one in
    the middle and a ring of ``n - 1`` at 0.55 of the half-image, all well inside it; depths
    drawn uniformly from 0.5-0.9 mm (seeded). The demo's and ``compare-modes``'s layout.

    Examples
    --------
    >>> depths, centres = press_ring((120, 160), 0.15, 6)
    >>> len(depths), centres[0], all(0.5 <= d <= 0.9 for d in depths)
    (6, (0.0, 0.0), True)
    """
    h, w = shape
    half_w, half_h = (w - 1) / 2 * mm_per_px, (h - 1) / 2 * mm_per_px
    rng = np.random.default_rng(seed)
    centres = [(0.0, 0.0)]
    for k in range(n - 1):
        a = 2 * np.pi * k / (n - 1)
        centres.append((0.55 * half_w * np.cos(a), 0.55 * half_h * np.sin(a)))
    depths = [float(d) for d in rng.uniform(0.5, 0.9, size=n)]
    return depths, centres


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
        Lighting mode (:func:`pipeline.base.modes.load_mode`).
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
    pipeline.base.store.Record
        Schema ``capture``: ``frames`` (K, P, H, W, 3), ``reference`` (P, H, W, 3), ``dark``
        (H, W, 3), ``drive`` (P, L, 3), ``brightness`` (P,), ``truth/height`` (K, H, W),
        ``truth/normals`` (K, H, W, 3), ``truth/albedo`` (H, W, 3); attributes
        ``mm_per_px``, ``pattern_names``, ``mode``, ``exposure``, ``bit_depth``,
        ``source='virtual'`` and ``render_settings``, ``illumination``.
    """
    from pipeline.base.store import Record

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


def save_png(path, image: np.ndarray) -> Path:
    """Write an RGB image (H, W, 3) as PNG: uint8/uint16 as they are, float clipped to 0..255 as uint8."""
    import cv2

    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"save_png: expected an RGB image (H, W, 3), got {img.shape}")
    if img.dtype not in (np.uint8, np.uint16):
        img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    path = Path(path)
    if not cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1])):  # OpenCV writes BGR
        from pipeline.base.errors import UserError

        raise UserError(f"{path}: could not write PNG")
    return path


def render_scene_files(out_dir, *, mode="monochromatic", height_file=None, height_scale: float = 1.0,
                       sphere_rd: tuple[float, float] | None = None, center=(0.0, 0.0),
                       shape: tuple[int, int] | None = None, mm_per_px: float = 0.0625, gel_z: float = 35.0,
                       settings_file=None, noise_dn: float = 1.0, bit_depth: int | None = 8, seed: int = 0,
                       name: str = "capture", illumination=None) -> dict:
    """Render a height map (file or sphere) under a mode to PNGs and a ``capture`` HDF5 file.

    The illumination is ``illumination`` (an ``illumination.h5`` from the ray tracer, whose
    pixel grid then sets ``shape`` and ``mm_per_px``) or else the bare-LED ring
    (:func:`sim.render.bare_ring_illumination`) at ``gel_z``. This is what
    ``iristac sim render`` runs.

    Parameters
    ----------
    out_dir : path
        Output folder (created).
    mode : str or path
        Lighting mode name or file.
    height_file : path, optional
        ``.npy`` or 16-bit ``.png`` height map (mm = value x ``height_scale``) at ``mm_per_px``.
    sphere_rd : (radius, depth), optional
        A sphere press instead of a file (``center`` in mm); neither: the flat gel.
    shape : (H, W), optional
        Image size (default: the file's, or 240 x 320).
    settings_file : path, optional
        A render settings YAML (``data_schemas/configs/render.json``); otherwise read noise
        ``noise_dn`` and ``bit_depth`` quantization with automatic exposure.

    Returns
    -------
    dict
        ``capture`` (path), ``pngs`` (paths), ``mode``, ``patterns``, ``shape``, ``mm_per_px``,
        ``exposure``, ``effects``.
    """
    from pipeline.base.errors import UserError
    from sim.geometry import height_from_file
    from sim.render import bare_ring_illumination, load_render_settings

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if height_file is not None and sphere_rd is not None:
        raise UserError("give either a height file or a sphere, not both")
    mode_obj = load_mode(mode)
    model = None
    if illumination is not None:
        from sim.synthesize import load_illumination

        model = load_illumination(illumination)
        shape, mm_per_px = model.shape, model.mm_per_px
    if height_file is not None:
        surface = height_from_file(height_file, mm_per_px, mm_per_unit=height_scale, shape=shape)
        shape, mm_per_px = surface.shape, surface.mm_per_px
    else:
        shape = tuple(shape) if shape is not None else (240, 320)
        surface = None
        if sphere_rd is not None:
            try:
                surface = sphere(shape, mm_per_px, float(sphere_rd[0]), float(sphere_rd[1]), center=tuple(center))
            except ValueError as exc:
                raise UserError(f"--sphere: {exc}") from None
    if model is None:
        model = bare_ring_illumination(shape, mm_per_px, gel_z)
    elif surface is not None and surface.shape != model.shape:
        raise UserError(f"{height_file}: height map is {surface.shape} pixels, the illumination model "
                        f"{illumination} is {model.shape}")
    settings = load_render_settings(settings_file) if settings_file is not None else None
    contacts = [surface] if surface is not None else []
    rec = render_capture(model, mode_obj, contacts, settings=settings, noise_dn=noise_dn, bit_depth=bit_depth,
                         seed=seed)
    pngs = []
    for p, pname in enumerate(mode_obj.pattern_names):
        if contacts:
            pngs.append(save_png(out / f"{name}_{pname}.png", rec.data["frames"][0, p]))
        pngs.append(save_png(out / f"reference_{pname}.png", rec.data["reference"][p]))
    pngs.append(save_png(out / "dark.png", rec.data["dark"]))
    from pipeline.base.capture import write_capture

    h5 = write_capture(out / f"{name}.h5", rec)
    return {"capture": str(h5), "pngs": [str(p) for p in pngs], "mode": mode_obj.name,
            "patterns": mode_obj.pattern_names, "shape": list(shape), "mm_per_px": float(mm_per_px),
            "exposure": rec.meta["exposure"], "effects": list(RenderSettings(**rec.meta["render_settings"]).effects)}
