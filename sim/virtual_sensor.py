"""A harder virtual tactile sensor: ball-press captures with a real sensor's flaws and exact truth.

The renderer (:class:`sim.render.Renderer`) draws each press of a ball of known radius; this
module gives it the look of a lab's own GelSight-type sensor and then the flaws real frames
have, each optional and computed only when the sensor asks for it
(:attr:`VirtualSensor.effects`, :attr:`SensorCapture.computed`):

``rim_smoothing``
    the gel's smoothing at the contact rim: the pressed surface (and so its exact truth) is
    the sphere cap blurred by a Gaussian (:func:`sim.geometry.smooth`), so near the rim it is
    no longer a sphere cap (the sphere truth of calibration stops being exact there);
``markers``
    printed dark dots on the gel (albedo, :func:`sim.sensor_effects.marker_coverage`);
``marker_motion``
    the dots carried by the gel under each press (radially outward around the contact,
    :func:`sim.sensor_effects.displace_markers`), so that a press's dots are not where the
    reference's are (needs ``markers``);
``vignetting``
    the renderer's lens fall-off (same in the reference and every press);
``soft_shading``
    a soft gel's look: the shading's change from the flat gel weaker and blurred
    (:func:`sim.sensor_effects.soften_shading`), and a white glossy highlight where the cap
    leans toward a light, a crescent at the contact's rim
    (:func:`sim.sensor_effects.rim_highlight`), brighter than the rest of the change;
``optical_blur``
    the optics' point spread, a Gaussian (:func:`sim.sensor_effects.optical_blur`; the DIGIT's
    frames are blurred by about 11 px);
``drift_gain``, ``drift_offset``, ``drift_field``
    illumination drift between the reference and each press: per-channel gain and offset
    (DN) and a smooth low-order multiplicative field, drawn per press;
``column_stripes``
    per-column offsets redrawn every frame;
``read_noise``
    Gaussian noise (DN);
``jpeg``
    JPEG compression of the stored 8-bit frame.

The illumination is GelSight-like by default (``lights="gelsight"``): one RGB frame per
press, lit by a red, a green and a blue LED beside the gel (near field, so the image has
strong colour gradients; closer lights, stronger gradients) plus a white light from below;
or any lighting mode of the 24-LED IrisTac ring (``lights="point"``, ``"trichromatic"``
...; several patterns per press). Any size (portrait or landscape; 120 x 160 to 640 x 480
and beyond), contacts from a fraction of the ball radius up to almost all of it, some of
them cut by the image border.

Truth (:class:`SensorTruth`), exact per pixel: each press's contact circle (centre and radius
in pixels), heights, normals and contact mask, the marker mask and coverage, and the drift
that was applied. :func:`random_sensor` draws a sensor from a seed (several sensors for a
benchmark, one small one for a test); :func:`write_sensor_capture` writes it as a capture
file (:func:`pipeline.base.capture.write_capture`) that ``calibrate`` and ``eval
calibration`` read, :func:`write_sensor_images` as a folder of image files that ``iristac
import images`` reads.

Examples
--------
>>> s = random_sensor(3, shape=(60, 80), num_presses=2)
>>> out = render_sensor(s)
>>> out.capture.frames.shape, out.capture.frames.dtype.name, out.truth.center_xy.shape
((2, 1, 60, 80, 3), 'uint8', (2, 2))
"""

from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.capture import Capture, write_capture
from pipeline.base.frames import pixel_to_recon
from pipeline.base.threads import limit_threads
from sim import sensor_effects as fx
from sim.geometry import sphere
from sim.illumination_model import IlluminationModel
from sim.point_source import point_source_field
from sim.render import Renderer, RenderSettings, auto_exposure, bare_ring_illumination

__all__ = ["VirtualSensor", "SensorTruth", "SensorCapture", "SENSOR_EFFECTS", "CONTACT_LOOK_EFFECTS", "press_layout", "random_sensor",
           "sibling_unit", "UNIT_VARIATION",
           "sensor_illumination", "render_sensor", "write_sensor_capture", "write_sensor_images"]

#: Optional effects of a virtual sensor, in the order they are applied.
SENSOR_EFFECTS = ("rim_smoothing", "markers", "marker_motion", "vignetting", "soft_shading", "optical_blur",
                  "drift_gain", "drift_offset", "drift_field", "column_stripes",
                  "read_noise", "jpeg")

#: The effects that change how a contact itself looks (what the edge detector alone misses).
CONTACT_LOOK_EFFECTS = ("marker_motion", "soft_shading")

#: Sizes :func:`random_sensor` draws from (rows, columns): portrait and landscape.
SIZES = ((120, 160), (160, 120), (240, 320), (320, 240), (480, 640), (640, 480))


@dataclass
class VirtualSensor:
    """Everything a virtual sensor's capture is made from (0 or None turns an effect off).

    Attributes
    ----------
    shape : (H, W)
        Image size (rows, columns).
    mm_per_px : float
    ball_radius_mm : float
    centers_xy : ndarray, shape (K, 2)
        Contact centres (x = column, y = row) in pixels, one per press.
    contact_radii_px : ndarray, shape (K,)
        Contact radii in pixels, each below the ball radius.
    lights : str
        ``"gelsight"``, or a lighting mode name or file of the 24-LED ring.
    light_azimuths_deg : (3,) floats
        Gelsight lights: where the red, green and blue LEDs sit, counter-clockwise on screen
        from the right.
    light_distance : float
        Gelsight lights: their distance from the image centre in half-diagonals of the image
        (below about 1.2 the gradients are strong).
    light_elevation_deg : float
        Gelsight lights: elevation seen from the image centre.
    ambient : float
        Gelsight lights: the white light from below, relative to a coloured one at the centre.
    target_dn : float
        The brightest flat-gel pixel before the effects (DN).
    drift_gain : float
        Per press and channel, gain ``1 + U(-drift_gain, drift_gain)``.
    drift_offset_dn : float
        Per press and channel, offset ``U(-drift_offset_dn, drift_offset_dn)`` DN.
    drift_field : float
        Per press, a smooth field (:data:`sim.sensor_effects.DRIFT_TERMS`) whose largest
        deviation from 1 is up to this.
    marker_spacing_px, marker_radius_px, marker_darkness : float
        Printed markers: grid pitch, dot radius (px) and how much light a dot absorbs (0..1).
    vignetting : float
        Strength of the renderer's ``vignetting`` effect.
    stripe_noise_dn : float
        Standard deviation of the per-column offsets (DN).
    read_noise_dn : float
        Gaussian noise (DN).
    jpeg_quality : int
        JPEG quality (1..100); 0 = frames stored losslessly.
    rim_smoothing_px : float
        Standard deviation (px) of the gel's smoothing of the pressed surface.
    blur_px : float
        Standard deviation (px) of the optical blur.
    marker_motion : float
        Markers' largest outward move under a press, as a fraction of its contact radius.
    soft_shading : float
        In [0, 1): the shading's change from the flat gel is scaled by ``1 - soft_shading``.
    soft_blur_px : float
        ... and blurred with this Gaussian sigma (px).
    rim_highlight_dn, rim_highlight_tilt_deg, rim_highlight_azimuth_deg, rim_highlight_sharpness : float
        The glossy highlight (:func:`sim.sensor_effects.rim_highlight`): peak (DN), where its
        half vector leans, and its lobe's exponent.
    seed : int
        Seed of every random draw of the rendering (drift, noise, marker jitter).
    """

    shape: tuple[int, int] = (120, 160)
    mm_per_px: float = 0.1
    ball_radius_mm: float = 2.0
    centers_xy: Any = ((80.0, 60.0),)
    contact_radii_px: Any = (12.0,)
    lights: str = "gelsight"
    light_azimuths_deg: tuple[float, float, float] = (0.0, 135.0, 270.0)
    light_distance: float = 1.5
    light_elevation_deg: float = 35.0
    ambient: float = 0.5
    target_dn: float = 200.0
    drift_gain: float = 0.0
    drift_offset_dn: float = 0.0
    drift_field: float = 0.0
    marker_spacing_px: float = 0.0
    marker_radius_px: float = 0.0
    marker_darkness: float = 0.7
    vignetting: float = 0.0
    stripe_noise_dn: float = 0.0
    read_noise_dn: float = 1.0
    jpeg_quality: int = 0
    seed: int = 0
    rim_smoothing_px: float = 0.0
    blur_px: float = 0.0
    marker_motion: float = 0.0
    soft_shading: float = 0.0
    soft_blur_px: float = 0.0
    rim_highlight_dn: float = 0.0
    rim_highlight_tilt_deg: float = 20.0
    rim_highlight_azimuth_deg: float = 0.0
    rim_highlight_sharpness: float = 60.0
    led_rgb: Any = None
    light_shift_px: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        self.shape = (int(self.shape[0]), int(self.shape[1]))
        h, w = self.shape
        if h < 8 or w < 8:
            raise ValueError(f"VirtualSensor: shape must be at least 8 x 8, got {self.shape}")
        for name in ("mm_per_px", "ball_radius_mm", "target_dn"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"VirtualSensor: {name} must be a finite number > 0, got {v!r}")
        for name in ("drift_gain", "drift_offset_dn", "drift_field", "marker_spacing_px", "marker_radius_px",
                     "vignetting", "stripe_noise_dn", "read_noise_dn", "ambient", "rim_smoothing_px", "blur_px"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"VirtualSensor: {name} must be a finite number >= 0, got {v!r}")
        if self.drift_gain >= 1 or self.drift_field >= 1:
            raise ValueError(f"VirtualSensor: drift_gain and drift_field must be < 1, got {self.drift_gain}, "
                             f"{self.drift_field}")
        self._check_contact_look()
        self._check_unit()
        if not 0 <= self.marker_darkness <= 1:
            raise ValueError(f"VirtualSensor: marker_darkness must be in [0, 1], got {self.marker_darkness}")
        if self.marker_spacing_px > 0 and not 0 < self.marker_radius_px < self.marker_spacing_px / 2:
            raise ValueError(f"VirtualSensor: markers need 0 < marker_radius_px < marker_spacing_px / 2, got "
                             f"{self.marker_radius_px} and {self.marker_spacing_px}")
        if not (self.jpeg_quality == 0 or 1 <= self.jpeg_quality <= 100):
            raise ValueError(f"VirtualSensor: jpeg_quality must be 0 (off) or 1..100, got {self.jpeg_quality}")
        c = np.asarray(self.centers_xy, np.float64).reshape(-1, 2)
        r = np.asarray(self.contact_radii_px, np.float64).reshape(-1)
        if len(c) != len(r):
            raise ValueError(f"VirtualSensor: {len(c)} centres but {len(r)} contact radii")
        if np.any(~np.isfinite(c)) or np.any(~(r > 0)) or np.any(r >= self.ball_radius_px):
            raise ValueError(f"VirtualSensor: contact radii must be in (0, {self.ball_radius_px:.2f}) px (the ball) "
                             f"and centres finite; got radii {np.round(r, 2).tolist()}")
        self.centers_xy, self.contact_radii_px = c, r

    def _check_unit(self):
        self.light_shift_px = (float(self.light_shift_px[0]), float(self.light_shift_px[1]))
        if not all(math.isfinite(v) for v in self.light_shift_px):
            raise ValueError(f"VirtualSensor: light_shift_px must be finite, got {self.light_shift_px}")
        if self.led_rgb is not None:
            rgb = np.asarray(self.led_rgb, np.float64)
            if rgb.shape != (4, 3) or not np.all(np.isfinite(rgb)) or np.any(rgb < 0) or np.any(rgb.sum(1) <= 0):
                raise ValueError(f"VirtualSensor: led_rgb must be a (4, 3) array of finite values >= 0 with light in "
                                 f"every row (red, green, blue LED, white light), got {np.asarray(self.led_rgb).tolist()}")
            self.led_rgb = rgb

    def _check_contact_look(self):
        for name in ("marker_motion", "soft_blur_px", "rim_highlight_dn", "rim_highlight_sharpness"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"VirtualSensor: {name} must be a finite number >= 0, got {v!r}")
        if not 0 <= self.soft_shading < 1:
            raise ValueError(f"VirtualSensor: soft_shading must be in [0, 1), got {self.soft_shading!r}")
        if self.marker_motion > 0 and self.marker_spacing_px <= 0:
            raise ValueError("VirtualSensor: marker_motion needs markers (marker_spacing_px > 0)")

    @property
    def ball_radius_px(self) -> float:
        """The ball's radius in pixels."""
        return self.ball_radius_mm / self.mm_per_px

    @property
    def num_presses(self) -> int:
        return int(len(self.contact_radii_px))

    @property
    def effects(self) -> tuple[str, ...]:
        """The optional effects this sensor turns on, in :data:`SENSOR_EFFECTS` order.

        Examples
        --------
        >>> VirtualSensor(jpeg_quality=80, drift_gain=0.1).effects
        ('drift_gain', 'read_noise', 'jpeg')
        """
        on = {"markers": self.marker_spacing_px > 0, "vignetting": self.vignetting > 0,
              "marker_motion": self.marker_motion > 0,
              "soft_shading": self.soft_shading > 0 or self.rim_highlight_dn > 0,
              "drift_gain": self.drift_gain > 0, "drift_offset": self.drift_offset_dn > 0,
              "drift_field": self.drift_field > 0, "column_stripes": self.stripe_noise_dn > 0,
              "read_noise": self.read_noise_dn > 0, "jpeg": self.jpeg_quality > 0,
              "rim_smoothing": self.rim_smoothing_px > 0, "optical_blur": self.blur_px > 0}
        return tuple(e for e in SENSOR_EFFECTS if on[e])

    def to_dict(self) -> dict:
        """JSON-able form; ``VirtualSensor(**d)`` rebuilds the sensor."""
        d = asdict(self)
        d["shape"] = list(self.shape)
        d["centers_xy"] = self.centers_xy.tolist()
        d["contact_radii_px"] = self.contact_radii_px.tolist()
        d["light_azimuths_deg"] = [float(a) for a in self.light_azimuths_deg]
        d["light_shift_px"] = [float(a) for a in self.light_shift_px]
        d["led_rgb"] = None if self.led_rgb is None else np.asarray(self.led_rgb).tolist()
        return d

    def replace(self, **changes) -> "VirtualSensor":
        """A copy with some fields changed (e.g. an effect turned off)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.update(changes)
        return VirtualSensor(**d)


@dataclass
class SensorTruth:
    """Exact truth of a rendered virtual sensor (K presses, image H x W).

    Attributes
    ----------
    center_xy : ndarray, shape (K, 2)
        Contact centres (x = column, y = row), pixels.
    radius_px : ndarray, shape (K,)
        Contact radii, pixels.
    ball_radius_px : float
    touches_border : ndarray, shape (K,), bool
        The contact circle leaves the image.
    height : ndarray, shape (K, H, W), float32
        mm, positive toward the camera.
    normals : ndarray, shape (K, H, W, 3), float32
        Reconstruction frame.
    contact : ndarray, shape (K, H, W), bool
        Pixels inside the contact.
    markers : ndarray, shape (H, W), bool, or None
        Pixels at least half covered by a printed marker.
    marker_coverage : ndarray, shape (H, W), float32, or None
        Fraction of each pixel covered.
    drift_gain, drift_offset : ndarray, shape (K, 3)
        Per press and channel (1 and 0 when off).
    drift_field_coeffs : ndarray, shape (K, 5)
        Per press (:func:`sim.sensor_effects.drift_field`; zeros when off).
    press_markers : ndarray, shape (K, H, W), bool, or None
        With ``marker_motion``: each press's marker mask (the dots where that press moved them).
    """

    center_xy: np.ndarray
    radius_px: np.ndarray
    ball_radius_px: float
    touches_border: np.ndarray
    height: np.ndarray
    normals: np.ndarray
    contact: np.ndarray
    markers: np.ndarray | None
    marker_coverage: np.ndarray | None
    drift_gain: np.ndarray
    drift_offset: np.ndarray
    drift_field_coeffs: np.ndarray
    press_markers: np.ndarray | None = None

    def drift_field(self, k: int) -> np.ndarray:
        """Press ``k``'s multiplicative drift field ``(H, W)``."""
        return fx.drift_field(self.height.shape[1:], self.drift_field_coeffs[k])

    def as_datasets(self) -> dict[str, np.ndarray]:
        """The ``truth/*`` datasets of the capture file (keys without the ``truth/`` prefix)."""
        out = {"height": self.height, "normals": self.normals, "contact": self.contact,
               "center_xy": self.center_xy.astype(np.float32), "radius_px": self.radius_px.astype(np.float32),
               "drift_gain": self.drift_gain.astype(np.float32), "drift_offset": self.drift_offset.astype(np.float32),
               "drift_field_coeffs": self.drift_field_coeffs.astype(np.float32)}
        if self.markers is not None:
            out["markers"] = self.markers
        return out


@dataclass
class SensorCapture:
    """What :func:`render_sensor` returns.

    Attributes
    ----------
    capture : pipeline.base.capture.Capture
        ``frames (K, P, H, W, 3)`` and ``reference (P, H, W, 3)`` uint8, the drive as an
        import of such frames has it (GelSight lights: three channel lights, as
        ``iristac import images`` makes), ``truth`` (:meth:`SensorTruth.as_datasets`),
        attributes ``ball_radius_mm``, ``frame_names`` and ``virtual_sensor`` (the sensor).
    truth : SensorTruth
    computed : list of str
        The optional effects actually computed (:data:`SENSOR_EFFECTS`).
    jpeg_bytes : list of bytes, or None
        With ``jpeg``: each stored frame's JPEG file, reference last (press-major, pattern-minor).
    """

    capture: Capture
    truth: SensorTruth
    computed: list[str]
    jpeg_bytes: list[bytes] | None = None


def press_layout(shape: tuple[int, int], ball_radius_px: float, num_presses: int, rng, *,
                 radius_range: tuple[float, float] = (0.3, 0.9), border_fraction: float = 0.0):
    """Random contact circles: ``(centers_xy (K, 2), radii_px (K,))``.

    Radii are ``U(radius_range) x ball_radius_px`` (capped so a circle fits the image);
    ``round(border_fraction * K)`` circles are cut by a random image border (their centre
    0.2 to 0.8 radii inside it), the rest lie inside the image with a 2 px margin.

    Examples
    --------
    >>> c, r = press_layout((60, 80), 10.0, 4, np.random.default_rng(0), border_fraction=0.5)
    >>> c.shape, bool(np.all((r >= 3) & (r <= 9)))
    ((4, 2), True)
    """
    h, w = int(shape[0]), int(shape[1])
    lo, hi = radius_range
    if not 0 < lo <= hi < 1:
        raise ValueError(f"press_layout: radius_range must satisfy 0 < lo <= hi < 1, got {radius_range}")
    r = rng.uniform(lo, hi, num_presses) * ball_radius_px
    r = np.minimum(r, (min(h, w) - 1) / 2 - 3)
    if np.any(r <= 0.5):
        raise ValueError(f"press_layout: a {h} x {w} image is too small for contacts of {ball_radius_px:.1f} px balls")
    n_border = int(round(border_fraction * num_presses))
    centers = np.empty((num_presses, 2))
    for k in range(num_presses):
        x = rng.uniform(r[k] + 2, w - 3 - r[k])
        y = rng.uniform(r[k] + 2, h - 3 - r[k])
        if k < n_border:
            inside = rng.uniform(0.2, 0.8) * r[k]
            side = int(rng.integers(4))
            if side == 0:
                x = inside
            elif side == 1:
                x = w - 1 - inside
            elif side == 2:
                y = inside
            else:
                y = h - 1 - inside
        centers[k] = (x, y)
    order = rng.permutation(num_presses)  # border presses anywhere in the sequence
    return centers[order], r[order]


def random_sensor(seed: int, *, shape: tuple[int, int] | None = None, num_presses: int = 8,
                  lights: str = "gelsight", effects: str | tuple[str, ...] | list[str] = "all",
                  border_fraction: float = 0.15, radius_range: tuple[float, float] = (0.3, 0.9)) -> VirtualSensor:
    """Draw a virtual sensor from ``seed``: size, pixel pitch, ball, lights, presses and effect strengths.

    Parameters
    ----------
    seed : int
        Same seed, same sensor (and, through ``VirtualSensor.seed``, the same frames).
    shape : (H, W), optional
        Default: one of :data:`SIZES` (portrait or landscape, 120 x 160 to 640 x 480).
    num_presses : int
    lights : str
        ``"gelsight"`` or a lighting mode of the 24-LED ring.
    effects : "all", "none" or a list of :data:`SENSOR_EFFECTS`
        Which effects to turn on (each at a random strength within what real sensors show:
        gain up to 15 %, offset up to 30 DN, drift field up to 8 %, markers 7-12 % of the
        short side apart, vignetting up to 0.4, stripes 1-3 DN, read noise 0.5-2 DN, JPEG
        quality 60-90, rim smoothing 3-8 % and optical blur 2-10 % of the ball radius in
        pixels, at least 1 px: the DIGIT's 11 px blur is 10 % of its 3 mm ball; markers moved by
        up to 15-30 % of the contact radius, and then darker (75-90 %) and larger (20-30 % of
        their spacing); soft shading at 30-50 % of its contrast, blurred by 5-10 % of the ball
        radius, with a highlight of 30-60 % of the gel's brightness). ``marker_motion`` turns
        ``markers`` on too.
    border_fraction, radius_range
        As :func:`press_layout`.

    Examples
    --------
    >>> s = random_sensor(1, effects=["jpeg", "markers"])
    >>> s.effects, s.shape in SIZES, s.to_dict() == random_sensor(1, effects=["jpeg", "markers"]).to_dict()
    (('markers', 'jpeg'), True, True)
    """
    on = set(SENSOR_EFFECTS) if effects == "all" else set() if effects == "none" else set(effects)
    unknown = on - set(SENSOR_EFFECTS)
    if unknown:
        raise ValueError(f"random_sensor: unknown effect(s) {sorted(unknown)} (known: {', '.join(SENSOR_EFFECTS)})")
    if "marker_motion" in on:
        on.add("markers")
    rng = np.random.default_rng([int(seed), 22])
    shape = tuple(SIZES[int(rng.integers(len(SIZES)))]) if shape is None else (int(shape[0]), int(shape[1]))
    short = min(shape)
    ball_mm = float(rng.choice([1.5, 2.0, 2.5, 3.0]))
    ball_px = float(rng.uniform(0.1, 0.22)) * short
    centers, radii = press_layout(shape, ball_px, num_presses, rng, radius_range=radius_range,
                                  border_fraction=border_fraction)
    phase = float(rng.uniform(0, 360))
    spacing = float(rng.uniform(0.07, 0.12)) * short
    kw: dict[str, Any] = dict(
        shape=shape, mm_per_px=ball_mm / ball_px, ball_radius_mm=ball_mm, centers_xy=centers, contact_radii_px=radii,
        lights=lights, light_azimuths_deg=tuple(float((phase + a + rng.uniform(-20, 20)) % 360) for a in (0, 135, 270)),
        light_distance=float(rng.uniform(1.0, 2.5)), light_elevation_deg=float(rng.uniform(25, 50)),
        ambient=float(rng.uniform(0.4, 1.2)), target_dn=float(rng.uniform(180, 240)), seed=int(rng.integers(1 << 30)),
        read_noise_dn=0.0)
    draws = {
        "drift_gain": ("drift_gain", float(rng.uniform(0.05, 0.15))),
        "drift_offset": ("drift_offset_dn", float(rng.uniform(10, 30))),
        "drift_field": ("drift_field", float(rng.uniform(0.03, 0.08))),
        "markers": ("marker_spacing_px", spacing),
        "vignetting": ("vignetting", float(rng.uniform(0.1, 0.4))),
        "column_stripes": ("stripe_noise_dn", float(rng.uniform(1.0, 3.0))),
        "read_noise": ("read_noise_dn", float(rng.uniform(0.5, 2.0))),
        "jpeg": ("jpeg_quality", int(rng.integers(60, 91))),
    }
    for effect, (name, value) in draws.items():  # every draw is made, so effects do not shift each other's values
        if effect in on:
            kw[name] = value
    if "markers" in on:
        kw["marker_radius_px"] = max(1.0, float(rng.uniform(0.12, 0.25)) * spacing)
        kw["marker_darkness"] = float(rng.uniform(0.5, 0.9))
    _draw_gel_optics(kw, on, rng, ball_px)
    kw.update(_contact_look_draws(seed, on, ball_px, kw))
    return VirtualSensor(**kw)


#: How much :func:`sibling_unit` lets one unit differ from another of the same design (each a
#: uniform draw within +-): the coloured LEDs' brightness (relative), the light they put in the
#: other two channels (up to, relative), the white light's tint per channel (relative), the
#: camera's rotation about its axis (deg, every light's azimuth), each LED's own azimuth (deg),
#: the lights' distance (relative) and elevation (deg), the camera's shift against the lights
#: (fraction of the short side), the gel's brightness (``target_dn``, relative) and the drift
#: strengths (relative).
UNIT_VARIATION = {"led_gain": 0.2, "led_crosstalk": 0.08, "white_tint": 0.15, "rotation_deg": 4.0,
                  "led_azimuth_deg": 3.0, "light_distance": 0.05, "light_elevation_deg": 2.0, "shift": 0.02,
                  "brightness": 0.1, "drift": 0.3}


def sibling_unit(sensor: VirtualSensor, unit_seed: int, *, num_presses: int | None = None,
                 border_fraction: float = 0.0, radius_range: tuple[float, float] = (0.3, 0.9),
                 variation: dict[str, float] | None = None) -> VirtualSensor:
    """Another unit of ``sensor``'s design: same build, its own LEDs, camera mount, gel and presses.

    Kept (the design): image size, pixel pitch, ball, the kind of lights and their nominal
    layout, the white light's level, every effect that is on and the gel's markers and look.
    Redrawn from ``unit_seed`` within :data:`UNIT_VARIATION` (or ``variation``, the same keys):
    each LED's brightness and colour (``led_rgb``: the coloured LEDs' gain and their light in
    the other channels, the white light's tint), the camera's pose against the lights (a
    rotation of every light's azimuth, each LED's own small misplacement, their distance and
    elevation, a shift ``light_shift_px``), the gel's brightness (``target_dn``), the drift
    strengths and every random draw of the rendering (``seed``), and the presses
    (:func:`press_layout`). Unit seed 0 is a unit too, not the design itself.

    Parameters
    ----------
    sensor : VirtualSensor
        The design (typically from :func:`random_sensor`; GelSight lights for the LED and mount
        variation, which the 24-LED ring's modes do not have: there only the gel, drift and
        presses change).
    unit_seed : int
    num_presses : int, optional
        Presses of the new unit (default: as many as ``sensor``).
    border_fraction, radius_range
        As :func:`press_layout`.
    variation : dict, optional
        Other limits than :data:`UNIT_VARIATION` (missing keys keep theirs; 0 turns one off).

    Returns
    -------
    VirtualSensor

    Examples
    --------
    >>> design = random_sensor(3, shape=(60, 80), num_presses=2, effects="none")
    >>> a, b = sibling_unit(design, 1), sibling_unit(design, 2)
    >>> (a.shape, a.ball_radius_mm, a.effects) == (design.shape, design.ball_radius_mm, design.effects)
    True
    >>> a.led_rgb.shape, bool(np.allclose(a.led_rgb, b.led_rgb)), a.to_dict() == sibling_unit(design, 1).to_dict()
    ((4, 3), False, True)
    """
    v = {**UNIT_VARIATION, **(variation or {})}
    unknown = set(v) - set(UNIT_VARIATION)
    if unknown:
        raise ValueError(f"sibling_unit: unknown variation key(s) {sorted(unknown)} (known: {', '.join(UNIT_VARIATION)})")
    rng = np.random.default_rng([int(unit_seed), 31])

    def u(key, size=None):
        return rng.uniform(-v[key], v[key], size)

    rgb = np.zeros((4, 3))
    rgb[:3] = rng.uniform(0.0, v["led_crosstalk"], (3, 3))
    rgb[np.arange(3), np.arange(3)] = 1.0 + u("led_gain", 3)
    rgb[3] = 1.0 + u("white_tint", 3)
    turn = float(u("rotation_deg"))
    az = tuple(float((a + turn + u("led_azimuth_deg")) % 360) for a in sensor.light_azimuths_deg)
    shift = tuple(float(x) for x in u("shift", 2) * min(sensor.shape))
    k = sensor.num_presses if num_presses is None else int(num_presses)
    centers, radii = press_layout(sensor.shape, sensor.ball_radius_px, k, rng, radius_range=radius_range,
                                  border_fraction=border_fraction)
    drift = 1.0 + u("drift", 3)
    return sensor.replace(
        led_rgb=rgb, light_azimuths_deg=az, light_shift_px=shift,
        light_distance=sensor.light_distance * (1.0 + float(u("light_distance"))),
        light_elevation_deg=sensor.light_elevation_deg + float(u("light_elevation_deg")),
        target_dn=sensor.target_dn * (1.0 + float(u("brightness"))),
        drift_gain=min(0.5, sensor.drift_gain * drift[0]), drift_offset_dn=sensor.drift_offset_dn * drift[1],
        drift_field=min(0.5, sensor.drift_field * drift[2]), seed=int(rng.integers(1 << 30)),
        centers_xy=centers, contact_radii_px=radii)


def _draw_gel_optics(kw: dict, on: set, rng, ball_px: float) -> None:
    """The rim smoothing and optical blur of :func:`random_sensor`, drawn after every other
    draw (so turning them on or off leaves the other effects' values as they were)."""
    # at least 1 px each: below that a small sensor's 8-bit frames would not show them
    smoothing = max(1.0, float(rng.uniform(0.03, 0.08)) * ball_px)
    blur = max(1.0, float(rng.uniform(0.02, 0.10)) * ball_px)
    if "rim_smoothing" in on:
        kw["rim_smoothing_px"] = smoothing
    if "optical_blur" in on:
        kw["blur_px"] = blur


def _contact_look_draws(seed: int, on: set[str], ball_px: float, kw: dict[str, Any]) -> dict[str, Any]:
    """:func:`random_sensor`'s draws for ``marker_motion`` and ``soft_shading``, from a generator of their own
    (so that sensors drawn without them keep every value they had)."""
    rng = np.random.default_rng([int(seed), 23])
    out: dict[str, Any] = {}
    motion = float(rng.uniform(0.15, 0.3))
    dark, size = float(rng.uniform(0.75, 0.9)), float(rng.uniform(0.2, 0.3))
    soft = float(rng.uniform(0.5, 0.7))
    blur = float(rng.uniform(0.05, 0.1)) * ball_px
    peak = float(rng.uniform(0.3, 0.6)) * kw["target_dn"]
    tilt = float(rng.uniform(15.0, 25.0))
    sharp = float(rng.uniform(40.0, 80.0))
    if "marker_motion" in on:  # the dark, large dots of the gels whose markers track shear
        out.update(marker_motion=motion, marker_darkness=dark, marker_radius_px=size * kw["marker_spacing_px"])
    if "soft_shading" in on:
        out.update(soft_shading=soft, soft_blur_px=blur, rim_highlight_dn=peak, rim_highlight_tilt_deg=tilt,
                   rim_highlight_azimuth_deg=float(kw["light_azimuths_deg"][0]), rim_highlight_sharpness=sharp)
    return out


def sensor_illumination(sensor: VirtualSensor) -> tuple[IlluminationModel, np.ndarray, np.ndarray, list[str]]:
    """The sensor's illumination: ``(model, drive (P, L, 3), brightness (P,), pattern names)``.

    ``"gelsight"``: a red, a green and a blue LED at ``light_azimuths_deg``, ``light_distance``
    half-diagonals from the image centre and ``light_elevation_deg`` below the gel, aimed at
    its centre, and a white LED far below the centre; each coloured LED's drive puts 1 on
    the flat gel's centre pixel, the white one ``ambient``. Otherwise the bare 24-LED ring
    (:func:`sim.render.bare_ring_illumination`) under the lighting mode ``sensor.lights``.
    """
    h, w = sensor.shape
    if sensor.lights != "gelsight":
        from pipeline.base.modes import load_mode, mode_brightness, mode_drive

        mode = load_mode(sensor.lights)
        model = bare_ring_illumination((h, w), sensor.mm_per_px, dtype=np.float32)
        return model, mode_drive(mode), mode_brightness(mode), list(mode.pattern_names)
    half_diag = math.hypot(h, w) / 2 * sensor.mm_per_px
    dist = sensor.light_distance * half_diag
    gel_z = dist * math.tan(math.radians(sensor.light_elevation_deg))
    az = np.deg2rad(np.asarray(sensor.light_azimuths_deg, np.float64))
    # Azimuths are on screen (recon frame, counter-clockwise from +x); optical y is recon -y.
    pos = np.stack([dist * np.cos(az), -dist * np.sin(az), np.zeros(3)], axis=-1)
    # A camera off the design's place sees every light moved (optical x along the columns, y down the rows).
    pos[:, :2] += np.asarray(sensor.light_shift_px) * sensor.mm_per_px
    axes = np.array([0.0, 0.0, gel_z]) - pos
    pos = np.vstack([pos, [0.0, 0.0, gel_z - 10 * half_diag]])
    axes = np.vstack([axes, [0.0, 0.0, 1.0]])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    V = point_source_field(pos, axes, (h, w), sensor.mm_per_px, gel_z, cone_half_angle_deg=89.0, dtype=np.float32)
    centre = V[:, h // 2, w // 2, 2].astype(np.float64)
    drive = np.zeros((1, 4, 3))
    drive[0, np.arange(3), np.arange(3)] = 1.0 / centre[:3]
    drive[0, 3, :] = sensor.ambient / centre[3]
    if sensor.led_rgb is not None:  # another unit's LEDs: other brightness and colour
        drive[0, :3, :] = sensor.led_rgb[:3] / centre[:3, None]
        drive[0, 3, :] = sensor.ambient * sensor.led_rgb[3] / centre[3]
    model = IlluminationModel(V=V, mm_per_px=sensor.mm_per_px, led_positions=pos, gel_z=gel_z,
                              meta={"source": "virtual_sensor"})
    return model, drive, np.ones(1), ["all-rgb"]


def _press_surfaces(sensor: VirtualSensor):
    h, w = sensor.shape
    R = sensor.ball_radius_mm
    a_mm = sensor.contact_radii_px * sensor.mm_per_px
    depths = R - np.sqrt(R * R - a_mm * a_mm)
    x, y = pixel_to_recon(sensor.centers_xy[:, 1], sensor.centers_xy[:, 0], (h, w), sensor.mm_per_px)
    caps = [sphere((h, w), sensor.mm_per_px, R, float(d), center=(float(cx), float(cy)))
            for d, cx, cy in zip(depths, np.atleast_1d(x), np.atleast_1d(y))]
    if "rim_smoothing" not in sensor.effects:
        return caps
    from sim.geometry import smooth

    return [smooth(c, sensor.rim_smoothing_px * sensor.mm_per_px) for c in caps]


def _drift_draws(sensor: VirtualSensor, rng):
    k = sensor.num_presses
    gain = 1 + rng.uniform(-sensor.drift_gain, sensor.drift_gain, (k, 3))
    offset = rng.uniform(-sensor.drift_offset_dn, sensor.drift_offset_dn, (k, 3))
    coeffs = np.zeros((k, len(fx.DRIFT_TERMS)))
    if sensor.drift_field > 0:
        basis = fx.drift_basis(sensor.shape).reshape(len(fx.DRIFT_TERMS), -1)
        for i in range(k):
            c = rng.uniform(-1, 1, len(fx.DRIFT_TERMS))
            peak = float(np.abs(c @ basis).max()) or 1.0
            coeffs[i] = c / peak * sensor.drift_field * rng.uniform(0.5, 1.0)
    return gain, offset, coeffs


class _ContactLook:
    """``marker_motion`` and ``soft_shading``: each press's own albedo (its moved dots) and its soft look."""

    def __init__(self, sensor: VirtualSensor, renderer, drive, bright, albedo, dots):
        self.s, self.renderer, self.drive, self.bright, self.base_albedo = sensor, renderer, drive, bright, albedo
        self.computed: list[str] = []
        self.masks: list[np.ndarray] = []
        self.dots = dots if sensor.marker_motion > 0 else None
        if self.dots is not None:
            self.computed.append("marker_motion")
        self._albedo: dict[int, Any] = {}

    def albedo(self, k: int):
        """Press ``k``'s albedo: the dots moved by its press (the sensor's dots when they do not move)."""
        s = self.s
        if self.dots is None:
            return self.base_albedo
        if k not in self._albedo:
            moved = fx.displace_markers(self.dots, s.centers_xy[k], s.contact_radii_px[k],
                                        s.marker_motion * s.contact_radii_px[k])
            cov = fx.dot_coverage(s.shape, moved, s.marker_radius_px)
            self.masks.append(cov >= 0.5)
            self._albedo[k] = 1.0 - s.marker_darkness * cov
        return self._albedo[k]

    def press(self, k: int, imgs: np.ndarray, surface) -> np.ndarray:
        s = self.s
        if s.soft_shading <= 0 and s.rim_highlight_dn <= 0:
            return imgs
        self.renderer.set_surface(None, self.albedo(k))
        flat = self.renderer.render(self.drive, self.bright)
        normals = np.asarray(surface.normals, np.float64)
        alb = np.asarray(self.albedo(k), np.float32)
        alb = alb[..., None] if alb.ndim == 2 else alb
        out = np.stack([fx.soften_shading(img, f, 1.0 - s.soft_shading, s.soft_blur_px)
                        + alb * self._highlight(normals) for img, f in zip(imgs, flat)])
        if "soft_shading" not in self.computed:
            self.computed.append("soft_shading")
        return out

    def _highlight(self, normals):
        s = self.s
        return fx.rim_highlight(normals, s.rim_highlight_tilt_deg, s.rim_highlight_azimuth_deg, s.rim_highlight_dn,
                                s.rim_highlight_sharpness)

    def reference(self, flat: np.ndarray) -> np.ndarray:
        s = self.s
        if s.rim_highlight_dn <= 0:
            return flat
        n = np.zeros(s.shape + (3,))
        n[..., 2] = 1.0
        alb = np.asarray(self.base_albedo, np.float32)
        alb = alb[..., None] if alb.ndim == 2 else alb
        return flat + alb * self._highlight(n)

    def press_markers(self) -> np.ndarray | None:
        return np.stack(self.masks) if self.masks else None


class _Camera:
    """The per-frame effects after the renderer, each run only when the sensor turns it on."""

    def __init__(self, sensor: VirtualSensor, gain, offset, coeffs):
        self.s, self.gain, self.offset, self.coeffs = sensor, gain, offset, coeffs
        self.computed: list[str] = []
        self.jpeg: list[bytes] = []

    def _mark(self, name):
        if name not in self.computed:
            self.computed.append(name)

    def frame(self, img: np.ndarray, press: int | None, rng) -> np.ndarray:
        s, on = self.s, self.s.effects
        if "optical_blur" in on:
            img = fx.optical_blur(img, s.blur_px)
            self._mark("optical_blur")
        if press is not None and ("drift_gain" in on or "drift_offset" in on or "drift_field" in on):
            field_map = None
            if "drift_field" in on:
                field_map = fx.drift_field(s.shape, self.coeffs[press])
                self._mark("drift_field")
            for name in ("drift_gain", "drift_offset"):
                if name in on:
                    self._mark(name)
            img = fx.apply_drift(img, self.gain[press] if "drift_gain" in on else None,
                                 self.offset[press] if "drift_offset" in on else None, field_map)
        if "column_stripes" in on:
            img = img + fx.column_stripes(s.shape, s.stripe_noise_dn, rng)
            self._mark("column_stripes")
        if "read_noise" in on:
            img = img + rng.normal(0.0, s.read_noise_dn, img.shape).astype(np.float32)
            self._mark("read_noise")
        out = fx.quantize_8bit(img)
        if "jpeg" in on:
            out, data = fx.jpeg_roundtrip(out, s.jpeg_quality)
            self.jpeg.append(data)
            self._mark("jpeg")
        return out


def render_sensor(sensor: VirtualSensor, device="cpu") -> SensorCapture:
    """Render every press and the reference of ``sensor``, with exact truth.

    The reference has the markers, vignetting, stripes, noise and JPEG of every frame but no
    drift: the drift of press ``k`` is relative to it. On the CPU it renders on one torch
    thread (:func:`pipeline.base.threads.limit_threads`: these frames are small, and two
    threads on a shared 2-core machine were 15x slower, measured).
    """
    if str(device) == "cpu":
        with limit_threads(torch=1):
            return _render_sensor(sensor, device)
    return _render_sensor(sensor, device)


def _render_sensor(sensor: VirtualSensor, device) -> SensorCapture:
    h, w = sensor.shape
    on = sensor.effects
    computed: list[str] = []
    rng = np.random.default_rng([sensor.seed, 7])
    gain, offset, coeffs = _drift_draws(sensor, rng)
    albedo: Any = 1.0
    coverage = markers = dots = None
    if "markers" in on:
        jitter = 0.1 * sensor.marker_spacing_px
        coverage, dots = fx.marker_coverage((h, w), sensor.marker_spacing_px, sensor.marker_radius_px,
                                         angle_deg=float(rng.uniform(-5, 5)), jitter_px=jitter,
                                         offset_px=tuple(rng.uniform(0, sensor.marker_spacing_px, 2)), rng=rng)
        albedo = 1.0 - sensor.marker_darkness * coverage
        markers = coverage >= 0.5
        computed.append("markers")
    model, drive, bright, pattern_names = sensor_illumination(sensor)
    settings = RenderSettings(exposure=auto_exposure(model, drive, bright, target_dn=sensor.target_dn),
                              vignetting=sensor.vignetting, bit_depth=None)
    renderer = Renderer(model, settings, device=device)
    if "vignetting" in on:
        computed.append("vignetting")
    if "rim_smoothing" in on:
        computed.append("rim_smoothing")
    camera = _Camera(sensor, gain, offset, coeffs)
    surfaces = _press_surfaces(sensor)
    look = _ContactLook(sensor, renderer, drive, bright, albedo, dots) if "marker_motion" in on or \
        "soft_shading" in on else None
    frames = np.empty((sensor.num_presses, len(pattern_names), h, w, 3), np.uint8)
    for k, surf in enumerate(surfaces):
        renderer.set_surface(surf, albedo if look is None else look.albedo(k))
        imgs = renderer.render(drive, bright)
        if look is not None:
            imgs = look.press(k, imgs, surf)
        frng = np.random.default_rng([sensor.seed, 1000 + k])
        frames[k] = [camera.frame(img, k, frng) for img in imgs]
    renderer.set_surface(None, albedo)
    frng = np.random.default_rng([sensor.seed, 999])
    flat = renderer.render(drive, bright)
    if look is not None:
        flat = look.reference(flat)
        computed += look.computed
    reference = np.stack([camera.frame(img, None, frng) for img in flat])
    computed += [e for e in camera.computed if e not in computed]
    computed.sort(key=SENSOR_EFFECTS.index)
    c, r = sensor.centers_xy, sensor.contact_radii_px
    truth = SensorTruth(
        center_xy=c.copy(), radius_px=r.copy(), ball_radius_px=sensor.ball_radius_px,
        touches_border=(c[:, 0] - r < 0) | (c[:, 1] - r < 0) | (c[:, 0] + r > w - 1) | (c[:, 1] + r > h - 1),
        height=np.stack([f.height for f in surfaces]).astype(np.float32),
        normals=np.stack([f.normals for f in surfaces]).astype(np.float32),
        contact=np.stack([f.contact for f in surfaces]), markers=markers, marker_coverage=coverage,
        drift_gain=gain if "drift_gain" in on else np.ones_like(gain),
        drift_offset=offset if "drift_offset" in on else np.zeros_like(offset),
        drift_field_coeffs=coeffs, press_markers=None if look is None else look.press_markers())
    if sensor.lights == "gelsight":  # as an import of RGB frames has it: the three channels are three lights
        cap_drive, cap_bright, mode = np.eye(3, dtype=np.float32)[None], np.ones(1, np.float32), "trichromatic"
    else:
        cap_drive, cap_bright, mode = drive.astype(np.float32), np.asarray(bright, np.float32), str(sensor.lights)
    meta = {"source": "virtual-sensor", "pattern_names": pattern_names, "mode": mode, "bit_depth": 8,
            "ball_radius_mm": float(sensor.ball_radius_mm), "frame_names": [f"press{k}" for k in range(len(c))],
            "virtual_sensor": sensor.to_dict()}
    cap = Capture(frames=frames, reference=reference, drive=cap_drive, brightness=cap_bright,
                  mm_per_px=float(sensor.mm_per_px), truth=truth.as_datasets(), meta=meta)
    return SensorCapture(cap, truth, computed, camera.jpeg if "jpeg" in on else None)


def write_sensor_capture(path, sensor: VirtualSensor, *, labels: bool = False, device="cpu") -> SensorCapture:
    """Render ``sensor`` and write it as a capture file (atomic, schema-checked).

    With ``labels=True`` the true circles are also stored as hand labels
    (``labels/center_xy``, ``labels/radius_px``), as a perfect labeller would have drawn them.
    Returns the :class:`SensorCapture`.
    """
    out = render_sensor(sensor, device=device)
    if labels:
        out.capture.labels = {"center_xy": out.truth.center_xy.astype(np.float32),
                              "radius_px": out.truth.radius_px.astype(np.float32)}
    write_capture(path, out.capture)
    return out


def write_sensor_images(folder, sensor: VirtualSensor, *, reference_index: int | None = None,
                        labels_csv: bool = True, device="cpu") -> dict:
    """Render ``sensor`` (one pattern) as the folder of image files ``iristac import images`` reads.

    Files ``frame_0 ... frame_K`` (``.jpg`` with the exact bytes of the ``jpeg`` effect,
    else ``.png``), one of them the no-contact reference (at ``reference_index``, default a
    seeded random position: no file name gives it away), and ``labels.csv`` with the true
    circles (``name,x,y,radius_px``, the format ``--labels`` reads).

    Returns
    -------
    dict
        ``folder``, ``files`` (names in order), ``reference`` (its name), ``press_names``,
        ``labels`` (CSV path or None), ``sensor_capture`` (the :class:`SensorCapture`).
    """
    import cv2

    out = render_sensor(sensor, device=device)
    cap = out.capture
    if cap.frames.shape[1] != 1:
        raise ValueError(f"write_sensor_images: one image per press needs one pattern, the sensor's lights "
                         f"{sensor.lights!r} have {cap.frames.shape[1]}")
    k = sensor.num_presses
    if reference_index is None:
        reference_index = int(np.random.default_rng([sensor.seed, 5]).integers(k + 1))
    if not 0 <= reference_index <= k:
        raise ValueError(f"write_sensor_images: reference_index must be in 0..{k}, got {reference_index}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ext = ".jpg" if out.jpeg_bytes is not None else ".png"
    order = list(range(k))
    order.insert(reference_index, -1)  # -1: the reference
    files, press_names = [], []
    for i, src in enumerate(order):
        name = f"frame_{i}{ext}"
        if out.jpeg_bytes is not None:
            (folder / name).write_bytes(out.jpeg_bytes[src])  # the reference's bytes are the last ones
        else:
            img = cap.reference[0] if src < 0 else cap.frames[src, 0]
            if not cv2.imwrite(str(folder / name), np.ascontiguousarray(img[..., ::-1])):
                raise OSError(f"{folder / name}: could not write the image")
        files.append(name)
        if src >= 0:
            press_names.append(name)
    csv_path = None
    if labels_csv:
        csv_path = folder / "labels.csv"
        with csv_path.open("w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["name", "x", "y", "radius_px"])
            for name, (x, y), r in zip(press_names, out.truth.center_xy, out.truth.radius_px):
                wr.writerow([name, f"{x:.3f}", f"{y:.3f}", f"{r:.3f}"])
    return {"folder": str(folder), "files": files, "reference": files[reference_index], "press_names": press_names,
            "labels": None if csv_path is None else str(csv_path), "sensor_capture": out}
