"""Photometric-stereo test objects with what real objects have: highlights, attached and cast
shadows, noise and 16-bit quantisation, written as a capture like an imported benchmark.

Objects (exact heights, gradients and normals, :class:`sim.geometry.HeightField`) sit on a
black background and are seen from above by an orthographic camera:

- :func:`sphere_object`: a ball (its visible hemisphere), DiLiGenT's "ball";
- :func:`bumpy_object`: the ball with steep Gaussian bumps (they cast shadows on it) and a
  varying colour.

:func:`render_ps_capture` renders one under far-field lights (:func:`sim.far_field.dome_lights`,
96 by default, within 45 degrees of the view axis) with the renderer's ``specular``
(Cook-Torrance lobe), ``cast_shadows``, ``shot_noise``, ``read_noise``, ``saturation`` and 16-bit
``quantization`` effects, and returns a schema-``capture`` record laid out like
:func:`pipeline.capture.diligent.diligent_record`'s: ``frames (1, P, H, W, 3)`` uint16, ``drive (P, P, 3)``
(light ``p`` alone at its RGB intensity), ``lights/light_vectors (P, 3, 3)`` (direction times
intensity), ``mask``, ``truth/normals``, ``truth/height``, ``truth/albedo``; no reference frames.
The object may be rendered in a small window and placed in a larger black frame
(``frame_shape``), so a 612 x 512 benchmark-sized capture costs only the object's pixels.

Examples
--------
>>> obj = sphere_object((24, 24), radius_px=10)
>>> d, e = dome_lights(4, 6)
>>> rec = render_ps_capture(obj, d, e, specular=0.04, seed=1)
>>> rec.data["frames"].shape, rec.data["frames"].dtype.name, int(rec.data["mask"].sum())
((1, 24, 24, 24, 3), 'uint16', 316)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.far_field import dome_lights, far_field_illumination
from sim.geometry.surface import HeightField, recon_grid
from sim.render import Renderer, RenderSettings

__all__ = ["PSObject", "sphere_object", "bumpy_object", "render_ps_capture", "write_ps_capture", "dome_lights",
           "OBJECTS"]


@dataclass
class PSObject:
    """An object to render: its surface, where it is, and its colour.

    Attributes
    ----------
    name : str
    field : HeightField
        Heights (mm; 0 on the background) and exact gradients.
    mask : ndarray, shape (H, W), bool
        The object's pixels (its silhouette).
    albedo : ndarray, shape (H, W, 3)
        RGB albedo (0 on the background: black cloth).
    """

    name: str
    field: HeightField
    mask: np.ndarray
    albedo: np.ndarray


def _ball(shape, mm_per_px: float, radius_px: float):
    """Height, gradients and mask of the visible hemisphere of a ball centred in the image."""
    x, y = recon_grid(shape, mm_per_px)
    R = radius_px * mm_per_px
    r2 = x * x + y * y
    inside = r2 < R * R
    z = np.sqrt(np.where(inside, R * R - r2, 1.0))  # > 0 at every pixel centre inside
    return np.where(inside, z, 0.0), np.where(inside, -x / z, 0.0), np.where(inside, -y / z, 0.0), inside, x, y


def sphere_object(shape=(160, 160), radius_px: float = 71.0, *, mm_per_px: float = 1.0,
                  albedo=(0.8, 0.6, 0.5)) -> PSObject:
    """A ball of ``radius_px`` pixels centred in the image (``pi R^2`` object pixels:
    71 px gives 15.8k, the size of DiLiGenT's objects).

    Examples
    --------
    >>> obj = sphere_object((9, 9), 3.5)
    >>> int(obj.mask.sum()), (obj.field.normals[4, 4] + 0.0).tolist()
    (37, [0.0, 0.0, 1.0])
    """
    if not 0 < 2 * radius_px <= min(shape):
        raise ValueError(f"sphere_object: radius_px must fit the image {tuple(shape)}, got {radius_px}")
    h, p, q, inside, _, _ = _ball(shape, mm_per_px, radius_px)
    rho = np.where(inside[..., None], np.asarray(albedo, dtype=np.float64), 0.0)
    return PSObject("sphere", HeightField(h, p, q, inside, mm_per_px), inside, rho)


def bumpy_object(shape=(160, 160), radius_px: float = 71.0, *, mm_per_px: float = 1.0, bumps: int = 12,
                 amplitude: float = 0.15, width: float = 0.05, seed: int = 0) -> PSObject:
    """The ball with ``bumps`` Gaussian bumps (height ``amplitude * R``, standard deviation
    ``width * R``: slopes up to about 1.8, steeper than the 45-degree lights, so they cast
    shadows: at the default size 16% of the object's pixels are in a cast shadow under some
    of the 96 dome lights) and a smoothly varying colour.

    Examples
    --------
    >>> obj = bumpy_object((40, 40), 18, bumps=4)
    >>> extra = obj.field.height - sphere_object((40, 40), 18).field.height
    >>> round(float(extra.max()), 1), float(obj.albedo[~obj.mask].max())
    (3.0, 0.0)
    """
    if not 0 < 2 * radius_px <= min(shape):
        raise ValueError(f"bumpy_object: radius_px must fit the image {tuple(shape)}, got {radius_px}")
    h, p, q, inside, x, y = _ball(shape, mm_per_px, radius_px)
    R = radius_px * mm_per_px
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, bumps)
    rad = R * np.sqrt(rng.uniform(0.0, 0.55, bumps))
    a, s = amplitude * R, width * R
    for cx, cy in zip(rad * np.cos(ang), rad * np.sin(ang)):
        g = a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        h = h + np.where(inside, g, 0.0)
        p = p + np.where(inside, -g * (x - cx) / (s * s), 0.0)
        q = q + np.where(inside, -g * (y - cy) / (s * s), 0.0)
    u = x / R
    rho = np.stack([0.55 + 0.3 * np.cos(3 * u), 0.5 + 0.25 * np.sin(2 * y / R + 1.0), 0.45 + 0.2 * u * u], -1)
    rho = np.where(inside[..., None], rho, 0.0)
    return PSObject("bumpy", HeightField(h, p, q, inside, mm_per_px), inside, rho)


#: Objects by name (the CLI's ``--object``).
OBJECTS = {"sphere": sphere_object, "bumpy": bumpy_object}


def render_ps_capture(obj: PSObject, directions, intensities, *, specular: float = 0.0, roughness: float = 0.3,
                      cast_shadows: bool = True, peak_dn: float = 30000.0, read_noise: float = 20.0,
                      shot_noise: float = 1.0, bit_depth: int = 16, frame_shape=None, offset=None, seed: int = 0,
                      device="cpu"):
    """Render ``obj`` under far-field lights as a schema-``capture`` record (module docstring).

    Parameters
    ----------
    obj : PSObject
    directions, intensities : ndarray, shape (P, 3)
        Unit directions toward the lights (reconstruction frame) and their RGB intensities
        (:func:`sim.far_field.dome_lights`). One image per light.
    specular, roughness : float
        Cook-Torrance lobe (``F0``, GGX roughness; ``specular=0``: Lambertian).
    cast_shadows : bool
        Shadows the object casts on itself (and on the black background).
    peak_dn : float
        Exposure: a Lambertian pixel of the object's largest albedo facing the brightest
        light head-on reads ``peak_dn``; highlights can exceed it and clip at full scale.
    read_noise, shot_noise : float
        Camera noise (DN; DN per electron), seeded by ``seed``.
    bit_depth : {8, 10, 12, 16}
    frame_shape : (H, W), optional
        Place the rendered object into a black frame of this size (default: the object's).
    offset : (row, col), optional
        Where the object's window goes in that frame (default: centred).

    Returns
    -------
    pipeline.base.store.Record
        Schema ``capture`` (attributes ``source = "synthetic-ps"``, ``object``, ``mm_per_px``,
        ``bit_depth``, ``exposure``, ``render_settings``, ``pattern_names``, ``mode = "point"``).
    """
    from pipeline.base.store import Record

    d = np.asarray(directions, dtype=np.float64)
    e = np.asarray(intensities, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or e.shape != d.shape:
        raise ValueError(f"render_ps_capture: directions and intensities must both have shape (P, 3), got "
                         f"{d.shape} and {e.shape}")
    P = len(d)
    h, w = obj.field.shape
    model = far_field_illumination(d, (h, w), obj.field.mm_per_px)
    d = model.directions
    exposure = peak_dn * np.pi / max(float(obj.albedo.max()) * float(e.max()), 1e-12)
    settings = RenderSettings(exposure=exposure, specular=specular, roughness=roughness, cast_shadows=cast_shadows,
                              read_noise=read_noise, shot_noise=shot_noise, saturation=True, bit_depth=bit_depth,
                              seed=seed)
    drive = np.zeros((P, P, 3))
    drive[np.arange(P), np.arange(P)] = e
    r = Renderer(model, settings, device=device)
    # The background is matte black cloth: no albedo and no lobe (a per-pixel material).
    r.set_surface(obj.field, obj.albedo, specular=np.where(obj.mask, specular, 0.0) if specular > 0 else None)
    window = r.render(drive)  # (P, h, w, 3)
    H, W = (h, w) if frame_shape is None else (int(frame_shape[0]), int(frame_shape[1]))
    if H < h or W < w:
        raise ValueError(f"render_ps_capture: frame_shape {(H, W)} is smaller than the object's window {(h, w)}")
    r0, c0 = ((H - h) // 2, (W - w) // 2) if offset is None else (int(offset[0]), int(offset[1]))
    if not (0 <= r0 <= H - h and 0 <= c0 <= W - w):
        raise ValueError(f"render_ps_capture: offset {(r0, c0)} puts the {h} x {w} window outside {(H, W)}")
    win = (slice(r0, r0 + h), slice(c0, c0 + w))

    def place(a, fill, dtype):
        out = np.empty((H, W) + a.shape[2:], dtype=dtype)
        out[...] = fill
        out[win] = a
        return out

    frames = np.zeros((1, P, H, W, 3), dtype=window.dtype)
    frames[0][:, win[0], win[1]] = window
    flat_n = np.array([0.0, 0.0, 1.0])
    normals = place(np.where(obj.mask[..., None], obj.field.normals, flat_n), flat_n, np.float32)
    data = {
        "frames": frames,
        "drive": drive.astype(np.float32),
        "brightness": np.ones(P, np.float32),
        "lights/light_vectors": (d[:, None, :] * e[:, :, None]).astype(np.float32),
        "mask": place(obj.mask, False, bool),
        "truth/normals": normals[None],
        "truth/height": place(obj.field.height, 0.0, np.float32)[None],
        "truth/albedo": place(obj.albedo, 0.0, np.float32),
    }
    meta = {"mm_per_px": float(obj.field.mm_per_px), "pattern_names": [f"light{p:03d}" for p in range(P)],
            "source": "synthetic-ps", "mode": "point", "bit_depth": int(bit_depth), "exposure": float(exposure),
            "object": obj.name, "render_settings": settings.to_dict(), "window": [int(r0), int(c0), int(h), int(w)]}
    return Record("capture", data, meta)


def write_ps_capture(out, object: str = "sphere", *, size: int = 160, radius_px: float = 71.0, frame=None,
                     lights=(8, 12), max_angle_deg: float = 45.0, specular: float = 0.04, roughness: float = 0.3,
                     cast_shadows: bool = True, read_noise: float = 20.0, shot_noise: float = 1.0,
                     seed: int = 0) -> dict:
    """Render a photometric-stereo object (``sphere`` or ``bumpy``) and write it as ``out``
    (``capture.h5``, atomically); the function behind ``iristac sim ps-object``.

    ``size`` is the object's square window, ``frame`` ``(H, W)`` the full image (default: the
    window), ``lights`` the ``(rows, cols)`` of the :func:`dome_lights` grid. Returns a summary
    with keys ``out``, ``object``, ``lights``, ``height``, ``width``, ``mask_pixels``,
    ``specular``, ``roughness``, ``effects``.

    Raises
    ------
    pipeline.base.errors.UserError
        An unknown object or impossible sizes, naming the option.
    """
    from pipeline.base.capture import write_capture
    from pipeline.base.errors import UserError

    if object not in OBJECTS:
        raise UserError(f"--object must be one of {', '.join(OBJECTS)}, got {object!r}")
    try:
        obj = OBJECTS[object]((size, size), radius_px, seed=seed) if object == "bumpy" else \
            OBJECTS[object]((size, size), radius_px)
        d, e = dome_lights(int(lights[0]), int(lights[1]), max_angle_deg, seed=seed)
        rec = render_ps_capture(obj, d, e, specular=specular, roughness=roughness, cast_shadows=cast_shadows,
                                read_noise=read_noise, shot_noise=shot_noise, frame_shape=frame, seed=seed)
    except ValueError as exc:
        raise UserError(f"sim ps-object: {exc}") from None
    path = write_capture(out, rec)
    _, P, H, W, _ = rec.data["frames"].shape
    return {"out": str(path), "object": object, "lights": int(P), "height": int(H), "width": int(W),
            "mask_pixels": int(rec.data["mask"].sum()), "specular": float(specular), "roughness": float(roughness),
            "effects": list(RenderSettings(**rec.meta["render_settings"]).effects)}
