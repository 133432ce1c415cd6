"""Synthetic sphere-indentation captures with exact truth (tests and benchmarks).

A thin wrapper over the project's one image-formation path, the renderer
:func:`sim.rendered_capture.render_capture`: it builds the illumination model (the closed-form
bare-LED ring field :func:`sim.point_source.point_source_field`, or with ``far_field=True``
each LED's field at the image centre everywhere), a lighting mode from a drive matrix, one
:func:`sim.geometry.sphere` press per requested contact circle, and turns the rendered
``capture`` record into a :class:`pipeline.base.capture.Capture` plus a :class:`SyntheticTruth`
that remembers what the frames were made from (fields, gains, exposure, LED geometry).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.base.capture import Capture
from pipeline.base.frames import pixel_to_recon
from pipeline.base.modes import LightingMode, ModeFrame
from sim.geometry import sphere
from sim.geometry.shapes import cap_depth
from sim.illumination_model import IlluminationModel
from sim.point_source import point_source_field, ring_geometry
from sim.render import RenderSettings, auto_exposure
from sim.rendered_capture import render_capture

__all__ = ["SyntheticTruth", "lighting_drive", "drive_mode", "ring_illumination", "synthetic_sphere_capture"]


@dataclass
class SyntheticTruth:
    """What a synthetic capture was made from.

    Attributes
    ----------
    centers_rc : ndarray, shape (K, 2)
        Contact centres (row, col) in pixels.
    radii_px : ndarray, shape (K,)
        Contact radii in pixels.
    V : ndarray, shape (L, H, W, 3)
        The flat-gel vector irradiance used for shading.
    gains : ndarray, shape (L, 3)
        Per-LED per-channel gains ``sigma``.
    exposure : float
        ``mu`` (chosen so that the brightest flat pixel is ``peak_dn``).
    led_positions, led_axes : ndarray, shape (L, 3)
        Optical frame.
    gel_z : float
    ball_radius_mm : float
    """

    centers_rc: np.ndarray
    radii_px: np.ndarray
    V: np.ndarray
    gains: np.ndarray
    exposure: float
    led_positions: np.ndarray
    led_axes: np.ndarray
    gel_z: float
    ball_radius_mm: float


def lighting_drive(mode: str, num_leds: int, leds: list[int] | None = None) -> np.ndarray:
    """Drive matrix ``(P, L, 3)`` of a named lighting mode.

    ``"point"``: one white LED per pattern (optionally only the LEDs listed in ``leds``).
    ``"trichromatic"``: one pattern, three equal sectors of the ring lit red, green and blue.

    Examples
    --------
    >>> lighting_drive("point", 4, leds=[0, 2]).shape
    (2, 4, 3)
    >>> lighting_drive("trichromatic", 6)[0].tolist()
    [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]
    """
    if mode == "point":
        idx = list(range(num_leds)) if leds is None else list(leds)
        drive = np.zeros((len(idx), num_leds, 3))
        for p, i in enumerate(idx):
            drive[p, i, :] = 1.0
        return drive
    if mode == "trichromatic":
        drive = np.zeros((1, num_leds, 3))
        sector = (np.arange(num_leds) * 3) // num_leds
        drive[0, np.arange(num_leds), sector] = 1.0
        return drive
    raise ValueError(f"lighting_drive: unknown mode {mode!r} (expected 'point' or 'trichromatic')")


def drive_mode(drive: np.ndarray, name: str = "custom", brightness=None) -> LightingMode:
    """A :class:`pipeline.base.modes.LightingMode` whose frame ``p`` drives the LEDs with ``drive[p]``.

    Examples
    --------
    >>> m = drive_mode(lighting_drive("point", 3))
    >>> m.num_leds, m.pattern_names
    (3, ['custom0', 'custom1', 'custom2'])
    """
    drive = np.asarray(drive, dtype=np.float64)
    if drive.ndim != 3 or drive.shape[2] != 3:
        raise ValueError(f"drive_mode: drive must have shape (P, L, 3), got {drive.shape}")
    b = np.ones(len(drive)) if brightness is None else np.asarray(brightness, dtype=np.float64).reshape(-1)
    return LightingMode(name, [ModeFrame(f"{name}{p}", drive[p], float(b[p])) for p in range(len(drive))])


def ring_illumination(shape: tuple[int, int], mm_per_px: float, num_leds: int = 6, ring_radius: float = 40.0,
                      gel_z: float = 30.0, far_field: bool = False, positions=None, axes=None) -> IlluminationModel:
    """Bare-LED ring illumination (closed form); ``far_field`` uses each LED's centre-pixel field everywhere.

    ``positions``/``axes`` (L, 3), optical frame, replace the regular ring when given.

    Examples
    --------
    >>> ring_illumination((4, 6), 0.1, 3).V.shape
    (3, 4, 6, 3)
    """
    h, w = int(shape[0]), int(shape[1])
    pos, ax = ring_geometry(num_leds, ring_radius)
    pos = pos if positions is None else np.asarray(positions, dtype=np.float64)
    ax = ax if axes is None else np.asarray(axes, dtype=np.float64)
    V = point_source_field(pos, ax, (h, w), mm_per_px, gel_z, dtype=np.float64)
    if far_field:
        V = np.broadcast_to(V[:, h // 2:h // 2 + 1, w // 2:w // 2 + 1, :], V.shape).copy()
    return IlluminationModel(V=V, mm_per_px=mm_per_px, led_positions=pos, gel_z=gel_z,
                             meta={"source": "bare_ring", "far_field": bool(far_field)})


def synthetic_sphere_capture(shape: tuple[int, int] = (60, 80), num_presses: int = 8, *,
                             mm_per_px: float = 0.1, ball_radius_mm: float = 1.5,
                             centers_rc=None, radii_px=None, num_leds: int = 6, ring_radius: float = 40.0,
                             gel_z: float = 30.0, mode: str = "point", leds: list[int] | None = None,
                             drive=None, gains=None, far_field: bool = False, albedo=1.0,
                             peak_dn: float = 200.0, noise_dn: float = 1.0, seed: int = 0,
                             illumination: IlluminationModel | None = None) -> tuple[Capture, SyntheticTruth]:
    """Render ``num_presses`` ball presses (8-bit, noisy) with exact truth.

    Parameters
    ----------
    shape : (H, W)
    num_presses : int
        K; ignored when ``centers_rc`` is given.
    mm_per_px, ball_radius_mm : float
    centers_rc : array_like, shape (K, 2), optional
        Press centres (row, col) in pixels; default: seeded uniform, away from the border.
    radii_px : array_like, shape (K,), optional
        Contact radii in pixels; default: seeded in [0.55, 0.8] x the ball radius.
    num_leds, ring_radius, gel_z : ring of bare LEDs (see :func:`sim.point_source.ring_geometry`).
    mode, leds : lighting mode for :func:`lighting_drive` (ignored when ``drive`` is given).
    drive : array_like, shape (P, L, 3), optional
    gains : array_like, shape (L, 3), optional
        Per-LED per-channel gains; default: seeded in [0.8, 1.2].
    far_field : bool
        Use each LED's field at the image centre at every pixel.
    albedo : float or ndarray (H, W) or (H, W, 3)
    peak_dn : float
        Brightest flat reference value before noise.
    noise_dn : float
        Gaussian read noise sigma in DN, before rounding to 8 bits.
    seed : int
    illumination : IlluminationModel, optional
        Render with this model instead of the bare ring (``num_leds``, ``ring_radius``,
        ``gel_z``, ``far_field`` are then ignored).

    Returns
    -------
    capture : Capture
        ``frames (K, P, H, W, 3)`` and ``reference (P, H, W, 3)`` uint8, with ``truth``.
    truth : SyntheticTruth

    Examples
    --------
    >>> cap, tr = synthetic_sphere_capture((30, 40), 2, ball_radius_mm=1.0, num_leds=3)
    >>> cap.frames.shape, cap.frames.dtype.name, tr.radii_px.shape
    ((2, 3, 30, 40, 3), 'uint8', (2,))
    """
    rng = np.random.default_rng(seed)
    h, w = int(shape[0]), int(shape[1])
    r_ball_px = ball_radius_mm / mm_per_px
    if radii_px is None:
        k = len(centers_rc) if centers_rc is not None else num_presses
        radii_px = rng.uniform(0.55, 0.8, size=k) * r_ball_px
    radii_px = np.asarray(radii_px, dtype=float).reshape(-1)
    if centers_rc is None:
        pad = radii_px + 2.0
        centers_rc = np.stack([rng.uniform(pad, h - 1 - pad), rng.uniform(pad, w - 1 - pad)], axis=-1)
    centers_rc = np.asarray(centers_rc, dtype=float).reshape(-1, 2)
    if len(radii_px) != len(centers_rc):
        raise ValueError(f"synthetic_sphere_capture: {len(centers_rc)} centres but {len(radii_px)} radii")
    if np.any(radii_px >= r_ball_px) or np.any(radii_px <= 0):
        raise ValueError(f"synthetic_sphere_capture: contact radii must be in (0, {r_ball_px:.2f}) px (the ball), "
                         f"got {radii_px.tolist()}")
    model = illumination if illumination is not None else ring_illumination(
        (h, w), mm_per_px, num_leds, ring_radius, gel_z, far_field)
    if model.shape != (h, w):
        raise ValueError(f"synthetic_sphere_capture: illumination is {model.shape} pixels, shape is {(h, w)}")
    n_led = model.num_leds
    drive = lighting_drive(mode, n_led, leds) if drive is None else np.asarray(drive, dtype=float)
    gains = rng.uniform(0.8, 1.2, size=(n_led, 3)) if gains is None else np.asarray(gains, dtype=float)
    exposure = auto_exposure(model, drive, target_dn=peak_dn, gains=gains)
    settings = RenderSettings(exposure=exposure, gains=gains, read_noise=float(noise_dn), saturation=True,
                              bit_depth=8)
    a_mm = radii_px * mm_per_px
    depths = cap_depth(ball_radius_mm, a_mm)
    x, y = pixel_to_recon(centers_rc[:, 0], centers_rc[:, 1], (h, w), mm_per_px)
    presses = [sphere((h, w), mm_per_px, ball_radius_mm, float(d), center=(float(cx), float(cy)))
               for d, cx, cy in zip(depths, np.atleast_1d(x), np.atleast_1d(y))]
    rec = render_capture(model, drive_mode(drive, mode), presses, albedo=albedo, settings=settings, dark=False,
                         seed=int(rng.integers(1 << 30)))
    d = rec.data
    cap = Capture(frames=d["frames"], reference=d["reference"], drive=d["drive"], brightness=d["brightness"],
                  mm_per_px=mm_per_px, truth={"height": d["truth/height"], "normals": d["truth/normals"]},
                  meta={"source": "virtual", "bit_depth": 8, "mode": mode,
                        "pattern_names": list(rec.meta["pattern_names"])})
    truth = SyntheticTruth(centers_rc=centers_rc, radii_px=radii_px, V=np.asarray(model.V, dtype=np.float64),
                           gains=gains, exposure=exposure, led_positions=np.asarray(model.led_positions),
                           led_axes=None if illumination is not None else ring_geometry(num_leds, ring_radius)[1],
                           gel_z=float(model.gel_z), ball_radius_mm=ball_radius_mm)
    return cap, truth
