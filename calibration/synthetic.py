"""Synthetic sphere-indentation captures with exact truth (tests and benchmarks).

Presses are shaded with the project's core formula :func:`sim.lambertian.shade` under the
closed-form bare-LED ring field :func:`sim.point_source.point_source_field` (or, with
``far_field=True``, each LED's field at the image centre everywhere), the truth surface is
:func:`calibration.truth.sphere_cap`, and the camera adds seeded Gaussian noise (default
sigma = 1 DN) and 8-bit quantization. Once the renderer (``sim.rendered_capture``) lands this
stays as the small closed-form reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.capture import Capture
from calibration.truth import sphere_cap
from sim.lambertian import shade
from sim.point_source import point_source_field, ring_geometry

__all__ = ["SyntheticTruth", "lighting_drive", "synthetic_sphere_capture"]


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


def synthetic_sphere_capture(shape: tuple[int, int] = (60, 80), num_presses: int = 8, *,
                             mm_per_px: float = 0.1, ball_radius_mm: float = 1.5,
                             centers_rc=None, radii_px=None, num_leds: int = 6, ring_radius: float = 40.0,
                             gel_z: float = 30.0, mode: str = "point", leds: list[int] | None = None,
                             drive=None, gains=None, far_field: bool = False, albedo=1.0,
                             peak_dn: float = 200.0, noise_dn: float = 1.0, seed: int = 0
                             ) -> tuple[Capture, SyntheticTruth]:
    """Render ``num_presses`` ball presses (8-bit, noisy) with exact truth.

    Parameters
    ----------
    shape : (H, W)
    num_presses : int
        K; ignored when ``centers_rc`` is given.
    mm_per_px, ball_radius_mm : float
    centers_rc : array_like, shape (K, 2), optional
        Press centres (row, col); default: seeded uniform, away from the border.
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
        Gaussian noise sigma in DN, before rounding to 8 bits.
    seed : int

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
    radii_px = np.asarray(radii_px, dtype=float)
    if centers_rc is None:
        pad = radii_px + 2.0
        centers_rc = np.stack([rng.uniform(pad, h - 1 - pad), rng.uniform(pad, w - 1 - pad)], axis=-1)
    centers_rc = np.asarray(centers_rc, dtype=float).reshape(-1, 2)
    if len(radii_px) != len(centers_rc):
        raise ValueError(f"synthetic_sphere_capture: {len(centers_rc)} centres but {len(radii_px)} radii")
    pos, axes = ring_geometry(num_leds, ring_radius)
    V = point_source_field(pos, axes, (h, w), mm_per_px, gel_z, dtype=np.float64)
    if far_field:
        V = np.broadcast_to(V[:, h // 2:h // 2 + 1, w // 2:w // 2 + 1, :], V.shape).copy()
    drive = lighting_drive(mode, num_leds, leds) if drive is None else np.asarray(drive, dtype=float)
    gains = rng.uniform(0.8, 1.2, size=(num_leds, 3)) if gains is None else np.asarray(gains, dtype=float)
    flat = np.zeros((h, w, 3))
    flat[..., 2] = 1.0
    ref = shade(V, flat, albedo, drive, gains=gains)
    exposure = peak_dn / float(ref.max())
    caps = [sphere_cap((h, w), c, r, ball_radius_mm, mm_per_px) for c, r in zip(centers_rc, radii_px)]
    frames = np.stack([shade(V, c.normals, albedo, drive, exposure=exposure, gains=gains) for c in caps])

    def camera(img):
        noisy = img + rng.normal(0.0, noise_dn, size=img.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)

    cap = Capture(frames=camera(frames), reference=camera(ref * exposure), drive=drive.astype(np.float32),
                  brightness=np.ones(len(drive), dtype=np.float32), mm_per_px=mm_per_px,
                  truth={"height": np.stack([c.height for c in caps]).astype(np.float32),
                         "normals": np.stack([c.normals for c in caps]).astype(np.float32)},
                  meta={"source": "virtual", "bit_depth": 8, "mode": mode})
    truth = SyntheticTruth(centers_rc=centers_rc, radii_px=radii_px, V=V, gains=gains, exposure=exposure,
                           led_positions=pos, led_axes=axes, gel_z=gel_z, ball_radius_mm=ball_radius_mm)
    return cap, truth
