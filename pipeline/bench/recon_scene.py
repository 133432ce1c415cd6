"""A rendered sphere indentation with exact truth, for the reconstruction tests and benchmark.

Built from the project's own physics (no renderer needed): the closed-form bare-LED ring
field (:func:`sim.point_source.point_source_field`), the core shading formula
(:func:`sim.lambertian.shade`) and exact sphere-cap normals; then optional Gaussian noise and
quantisation to the camera's bit depth. Lighting: ``P`` white sectors of the 24-LED ring
(the paper's monochromatic mode), so each pattern has its own light direction and the three
camera channels are three observations under it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.base.frames import pixel_to_recon
from sim.illumination_model import light_matrices
from sim.lambertian import shade
from sim.point_source import point_source_field, ring_geometry

__all__ = ["SphereScene", "sphere_cap", "sector_drive", "render_sphere_scene"]


def sphere_cap(shape: tuple[int, int], mm_per_px: float, radius: float, depth: float, center=(0.0, 0.0)):
    """Height ``(H, W)`` (mm) and exact unit normals ``(H, W, 3)`` of a ball pressed into the gel.

    The ball of ``radius`` mm is pressed ``depth`` mm into a flat gel; the gel takes the cap's
    shape inside the contact circle (a bump toward the camera) and stays flat outside.
    ``center`` is the contact centre in reconstruction-frame mm.

    Examples
    --------
    >>> h, n = sphere_cap((5, 5), 0.5, 2.0, 0.5)
    >>> float(h[2, 2]), (n[2, 2] + 0.0).tolist(), n[0, 0].tolist()
    (0.5, [0.0, 0.0, 1.0], [0.0, 0.0, 1.0])
    """
    if not (0 < depth <= radius):
        raise ValueError(f"sphere_cap: need 0 < depth <= radius, got depth={depth}, radius={radius}")
    rows, cols = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    x, y = pixel_to_recon(rows, cols, shape, mm_per_px)
    x, y = x - center[0], y - center[1]
    r2 = x * x + y * y
    inside = r2 < radius * radius - (radius - depth) ** 2
    zc = -(radius - depth)  # sphere centre below the gel surface
    z = np.sqrt(np.clip(radius * radius - r2, 0.0, None)) + zc
    h = np.where(inside, z, 0.0)
    n = np.stack([x, y, z - zc], axis=-1) / radius
    n = np.where(inside[..., None], n, np.array([0.0, 0.0, 1.0]))
    return h, n


def sector_drive(num_patterns: int, num_leds: int = 24) -> np.ndarray:
    """Drive ``(P, L, 3)``: pattern ``p`` lights the ``p``-th of ``P`` equal ring sectors white.

    Examples
    --------
    >>> d = sector_drive(4, 8)
    >>> d[:, :, 0].astype(int).tolist()[1]
    [0, 0, 1, 1, 0, 0, 0, 0]
    """
    drive = np.zeros((num_patterns, num_leds, 3))
    sector = (np.arange(num_leds) * num_patterns) // num_leds
    drive[sector, np.arange(num_leds), :] = 1.0
    return drive


@dataclass
class SphereScene:
    """Everything a reconstruction test needs. Shapes: ``P`` patterns, ``C = 3`` channels.

    frames (P, H, W, 3) contact frames (float64 noiseless, or quantised values as float64);
    reference (P, H, W, 3) no-contact frames; lights (P, 3, H, W, 3) per-pixel light matrices;
    V (L, H, W, 3); drive (P, L, 3); height (H, W) mm; normals (H, W, 3); albedo (H, W, 3).
    """

    frames: np.ndarray
    reference: np.ndarray
    lights: np.ndarray
    V: np.ndarray
    drive: np.ndarray
    height: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    mm_per_px: float
    depth: float
    exposure: float

    @property
    def observations(self) -> np.ndarray:
        """Frames as solver observations ``(P*3, H, W)``."""
        P, H, W, C = self.frames.shape
        return self.frames.transpose(0, 3, 1, 2).reshape(P * C, H, W)

    def lights_flat(self) -> np.ndarray:
        """Per-pixel lights as ``(P*3, H, W, 3)``."""
        P, C, H, W, _ = self.lights.shape
        return self.lights.reshape(P * C, H, W, 3)

    def lights_far(self) -> np.ndarray:
        """Far-field approximation ``(P*3, 3)``: each light vector at the image centre."""
        P, C, H, W, _ = self.lights.shape
        return self.lights[:, :, H // 2, W // 2, :].reshape(P * C, 3)


def render_sphere_scene(shape=(60, 80), mm_per_px: float = 0.1, *, radius: float = 3.0, depth: float = 0.5,
                        num_patterns: int = 8, gel_z: float = 30.0, peak: float = 200.0, noise: float = 0.0,
                        bits: int | None = None, albedo=(0.9, 0.8, 0.7), seed: int = 0,
                        dtype=np.float64) -> SphereScene:
    """Render a ball pressed into the gel under ``num_patterns`` white ring sectors.

    Parameters
    ----------
    shape, mm_per_px : image size and pixel pitch (the gel patch is centred on the ring axis).
    radius, depth : ball radius and indentation depth (mm).
    gel_z : optical ``z`` of the gel (mm) above the bare LED ring (24 LEDs, radius 40 mm).
    peak : exposure is set so the brightest flat-gel value is ``peak`` (DN).
    noise : Gaussian noise sigma (DN), seeded by ``seed``.
    bits : quantise and clip to ``[0, 2**bits - 1]`` when given.
    albedo : RGB albedo of the gel (uniform).

    Examples
    --------
    >>> s = render_sphere_scene((12, 16), 0.5, radius=2.0, depth=0.5, num_patterns=4)
    >>> s.frames.shape, s.lights.shape, round(float(s.reference.max()), 6)
    ((4, 12, 16, 3), (4, 3, 12, 16, 3), 200.0)
    """
    pos, axes = ring_geometry(24, 40.0)
    V = point_source_field(pos, axes, shape, mm_per_px, gel_z, dtype=np.float64)
    drive = sector_drive(num_patterns, 24)
    h, n = sphere_cap(shape, mm_per_px, radius, depth)
    rho = np.broadcast_to(np.asarray(albedo, dtype=np.float64), shape + (3,)).copy()
    flat = np.zeros(shape + (3,))
    flat[..., 2] = 1.0
    ref = shade(V, flat, rho, drive)
    exposure = peak / float(ref.max())
    ref = ref * exposure
    img = shade(V, n, rho, drive, exposure=exposure)
    rng = np.random.default_rng(seed)
    out = []
    for a in (img, ref):
        if noise > 0:
            a = a + rng.normal(0.0, noise, a.shape)
        if bits is not None:
            a = np.clip(np.round(a), 0, 2 ** bits - 1)
        out.append(a.astype(dtype))
    # The solver's light vectors carry rho/pi from the shading formula's 1/pi and exposure.
    lights = light_matrices(V, drive, exposure=exposure / np.pi).astype(dtype)
    return SphereScene(frames=out[0], reference=out[1], lights=lights, V=V.astype(dtype), drive=drive, height=h,
                       normals=n, albedo=rho, mm_per_px=mm_per_px, depth=depth, exposure=exposure)


def scene_records(scene: SphereScene, *, bits: int = 8, num_presses: int = 1):
    """The scene as stage-store records: ``(capture, illumination, calibration)``.

    The capture holds ``num_presses`` copies of the contact frames (uint8/uint16 when the scene
    was quantised) with truth; the illumination holds the bare-ring ``V``; the calibration holds
    the exact light field and the centre-pixel far-field vectors (what a perfect calibration
    of this scene would give).
    """
    from pipeline.base.store import Record

    P, H, W, C = scene.frames.shape
    dt = np.uint8 if bits <= 8 else np.uint16
    k = num_presses
    capture = Record("capture", {
        "frames": np.repeat(np.clip(np.round(scene.frames), 0, 2 ** bits - 1).astype(dt)[None], k, 0),
        "reference": np.clip(np.round(scene.reference), 0, 2 ** bits - 1).astype(dt),
        "drive": scene.drive.astype(np.float32),
        "brightness": np.ones(P, np.float32),
        "truth/height": np.repeat(scene.height.astype(np.float32)[None], k, 0),
        "truth/normals": np.repeat(scene.normals.astype(np.float32)[None], k, 0),
        "truth/albedo": scene.albedo.astype(np.float32),
    }, {"mm_per_px": scene.mm_per_px, "pattern_names": [f"sector{p}" for p in range(P)], "source": "virtual",
        "mode": "monochromatic", "exposure": float(scene.exposure), "bit_depth": int(bits)})
    pos, _ = ring_geometry(24, 40.0)
    illumination = Record("illumination", {"V": scene.V.astype(np.float32), "led_positions": pos},
                          {"mm_per_px": scene.mm_per_px, "gel_z": 30.0, "scene": "bare-ring"})
    lf = scene.lights.astype(np.float32)
    calibration = Record("calibration", {
        "circles": np.zeros((k, 8), np.float32),
        "light_field": lf,
        "light_vectors": lf[:, :, H // 2, W // 2, :].copy(),
    }, {"mm_per_px": scene.mm_per_px, "ball_radius_mm": 3.0, "models": ["exact"]})
    return capture, illumination, calibration
