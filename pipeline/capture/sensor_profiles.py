"""Sensor profiles: a tactile sensor described by a small YAML file (``pipeline/capture/sensors/*.yaml``).

A profile says which camera the sensor is (a device-name pattern, matched against
``/dev/v4l/by-id`` by :func:`pipeline.capture.camera_names.find_camera`), how its stream
becomes the images the pipeline works on (``crop``, ``rotate``, resized to ``resolution``),
their pixel pitch on the gel (``mm_per_px``), the ball it is calibrated with
(``ball_radius_mm``) and, where measured, the illumination drift its calibration removes
(``calibration_drift``) and the size of the MLP ensemble it fits (``calibration_mlp_members``);
schema ``data_schemas/configs/sensor.json``. Built in: ``gelsight-mini``, ``digit``,
``iristac-ring``; any other file with the same keys is a profile too.

``iristac import images --profile``, ``calibrate --profile`` and ``live --profile`` take a
name or a file (:func:`load_profile`).

Examples
--------
>>> p = load_profile("digit")
>>> p.make, p.resolution, p.mm_per_px, p.ball_radius_mm
('Meta AI / GelSight Inc. DIGIT', (480, 640), 0.0266, 3.0)
>>> p.to_image(np.zeros((480, 640, 3), np.uint8)).shape      # a VGA frame, turned portrait
(640, 480, 3)
>>> list_profiles()
['digit', 'gelsight-mini', 'iristac-ring']
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.base.camera import MappedCamera
from pipeline.base.errors import UserError

__all__ = ["SensorProfile", "ProfileCamera", "load_profile", "list_profiles", "profiles_of_size", "capture_defaults",
           "camera_source", "PROFILES_DIR"]

#: Folder of the built-in profiles.
PROFILES_DIR = Path(__file__).resolve().parent / "sensors"


#: The profile's calibration settings a capture records at import (a user's profile file is not
#: found by its name later) and ``calibrate`` reads back (:func:`capture_setting`).
RECORDED_SETTINGS = ("calibration_drift", "calibration_mlp_members")


@dataclass(frozen=True)
class SensorProfile:
    """One sensor (see the module docstring). Sizes are ``(width, height)``; ``crop`` is
    ``(x, y, width, height)`` in stream pixels."""

    name: str
    make: str
    resolution: tuple[int, int]
    mm_per_px: float
    ball_radius_mm: float
    camera: str | None = None
    stream: tuple[int, int] | None = None
    crop: tuple[int, int, int, int] | None = None
    rotate: int = 0
    mode: str | None = None
    calibration_drift: str | None = None
    calibration_mlp_members: int | None = None
    notes: str = ""
    source: str = ""

    def recorded_settings(self) -> dict:
        """The :data:`RECORDED_SETTINGS` this profile sets, as a capture records them.

        >>> load_profile("digit").recorded_settings()
        {'calibration_drift': 'field', 'calibration_mlp_members': 3}
        """
        return {k: getattr(self, k) for k in RECORDED_SETTINGS if getattr(self, k) is not None}

    def to_image(self, frame: np.ndarray) -> np.ndarray:
        """One stream frame ``(H, W, C)`` as the pipeline's image: cropped, rotated, resized to
        :attr:`resolution` (area interpolation when shrinking); a frame already of that size is
        returned as it is."""
        import cv2

        f = np.asarray(frame)
        w, h = self.resolution
        if f.shape[:2] == (h, w):
            return f
        if self.crop is not None:
            x, y, cw, ch = self.crop
            if x + cw > f.shape[1] or y + ch > f.shape[0]:
                raise UserError(f"sensor profile {self.name!r} ({self.source}): crop {self.crop} does not fit a "
                                f"{f.shape[1]} x {f.shape[0]} frame")
            f = f[y:y + ch, x:x + cw]
        if self.rotate:
            f = np.rot90(f, k=self.rotate // 90)
        if f.shape[:2] != (h, w):
            shrink = f.shape[0] * f.shape[1] > h * w
            out = cv2.resize(np.ascontiguousarray(f), (w, h), interpolation=cv2.INTER_AREA if shrink else
                             cv2.INTER_LINEAR)
            f = out[..., None] if out.ndim == 2 else out
        return np.ascontiguousarray(f)

    def fit_frames(self, frames: np.ndarray, where: str = "frames") -> np.ndarray:
        """Frames ``(..., H, W, C)`` of the stream (converted) or of the profile's resolution
        (kept); any other size is a :class:`UserError` naming both."""
        f = np.asarray(frames)
        w, h = self.resolution
        size = f.shape[-3:-1]
        if size == (h, w):
            return f
        if self.stream is not None and size == (self.stream[1], self.stream[0]):
            flat = f.reshape((-1,) + f.shape[-3:])
            out = np.stack([self.to_image(x) for x in flat])
            return out.reshape(f.shape[:-3] + out.shape[-3:])
        want = f"{w} x {h}" + (f" (or the stream's {self.stream[0]} x {self.stream[1]})" if self.stream else "")
        raise UserError(f"{where}: frames are {size[1]} x {size[0]} px, but sensor profile {self.name!r} "
                        f"({self.source}) expects {want}")


def list_profiles() -> list[str]:
    """Names of the built-in profiles."""
    return sorted(p.stem for p in PROFILES_DIR.glob("*.yaml"))


def capture_setting(meta: dict, key: str):
    """A profile setting (one of :data:`RECORDED_SETTINGS`) for a capture with attributes
    ``meta``: the value it recorded at import, else that of the built-in profile it names
    (imported before the key was recorded), else None.

    >>> capture_setting({"sensor_profile": "lab-gel", "calibration_drift": "offset"}, "calibration_drift")
    'offset'
    >>> capture_setting({"sensor_profile": "digit"}, "calibration_mlp_members")
    3
    >>> capture_setting({}, "calibration_drift") is None
    True
    """
    if key not in RECORDED_SETTINGS:
        raise ValueError(f"capture_setting: key must be one of {', '.join(RECORDED_SETTINGS)}, got {key!r}")
    if meta.get(key) is not None:
        return meta[key]
    name = meta.get("sensor_profile")
    return getattr(load_profile(str(name)), key) if name and str(name) in list_profiles() else None


def profiles_of_size(width: int, height: int) -> list[str]:
    """Built-in profiles whose images are ``width x height`` (a hint for an import without ``--profile``).

    >>> profiles_of_size(480, 640), profiles_of_size(160, 120)
    (['digit'], [])
    """
    return [n for n in list_profiles() if load_profile(n).resolution == (int(width), int(height))]


def load_profile(name_or_path) -> SensorProfile:
    """A built-in profile by name, or a profile file; errors name the file and the key.

    Examples
    --------
    >>> load_profile("nope")
    Traceback (most recent call last):
    ...
    pipeline.base.errors.UserError: no sensor profile 'nope': built in are digit, gelsight-mini, iristac-ring, ...
    """
    import data_schemas

    if isinstance(name_or_path, SensorProfile):
        return name_or_path
    text = str(name_or_path)
    path = Path(text)
    if not path.is_file():
        if text in list_profiles():
            path = PROFILES_DIR / f"{text}.yaml"
        else:
            raise UserError(f"no sensor profile {text!r}: built in are {', '.join(list_profiles())}, or give a "
                            "profile file (.yaml)")
    try:
        obj = data_schemas.load_config_file("sensor", path)
    except data_schemas.SchemaError as exc:
        raise UserError(str(exc)) from None
    res = (int(obj["resolution"]["width"]), int(obj["resolution"]["height"]))
    stream = (int(obj["stream"]["width"]), int(obj["stream"]["height"])) if "stream" in obj else None
    crop = tuple(int(obj["crop"][k]) for k in ("x", "y", "width", "height")) if "crop" in obj else None
    if crop is not None and stream is not None and (crop[0] + crop[2] > stream[0] or crop[1] + crop[3] > stream[1]):
        raise UserError(f"{path}: crop {crop} (x, y, width, height) does not fit the {stream[0]} x {stream[1]} stream")
    return SensorProfile(name=obj["name"], make=obj["make"], resolution=res, mm_per_px=float(obj["mm_per_px"]),
                         ball_radius_mm=float(obj["ball_radius_mm"]), camera=obj.get("camera"), stream=stream,
                         crop=crop, rotate=int(obj.get("rotate", 0)), mode=obj.get("mode"),
                         calibration_drift=obj.get("calibration_drift"),
                         calibration_mlp_members=(None if obj.get("calibration_mlp_members") is None
                                                  else int(obj["calibration_mlp_members"])),
                         notes=str(obj.get("notes", "")).strip(), source=str(path))


def capture_defaults(profile, capture_path, ball_radius_mm: float | None = None,
                     mm_per_px: float | None = None) -> tuple[float, float]:
    """``(ball_radius_mm, mm_per_px)`` for calibrating ``capture_path`` with ``profile``: the
    given values, else the profile's; the capture's images must be of the profile's resolution
    (else its pixel pitch does not apply: a :class:`UserError` naming both sizes)."""
    from pipeline.base.store import describe_file

    p = load_profile(profile)
    description, _ = describe_file(capture_path)
    shape = description["datasets"].get("frames", {}).get("shape")
    if not shape or len(shape) != 5:
        raise UserError(f"{capture_path}: not a capture (no (K, P, H, W, C) 'frames')")
    if (shape[3], shape[2]) != p.resolution:
        raise UserError(f"{capture_path}: images are {shape[3]} x {shape[2]} px, sensor profile {p.name!r} is for "
                        f"{p.resolution[0]} x {p.resolution[1]} (import the frames with --profile {p.name}, or give "
                        "--mm-per-px and --ball-radius)")
    return (float(ball_radius_mm) if ball_radius_mm is not None else p.ball_radius_mm,
            float(mm_per_px) if mm_per_px is not None else p.mm_per_px)


class ProfileCamera(MappedCamera):
    """A camera (:class:`pipeline.base.camera.Camera`) whose frames become a profile's images
    (:meth:`SensorProfile.fit_frames`: cropped, rotated, resized)."""

    def __init__(self, camera, profile):
        super().__init__(camera)
        self.profile = load_profile(profile)

    def map_image(self, image: np.ndarray) -> np.ndarray:
        return self.profile.fit_frames(image, f"camera {getattr(self.camera, 'source', '')}".strip())

    @property
    def shape(self) -> tuple[int, int]:
        w, h = self.profile.resolution
        return h, w

    def __str__(self) -> str:
        return f"{getattr(self.camera, 'source', self.camera)} (sensor profile {self.profile.name})"


def camera_source(source=None, profile=None, by_id_dir=None):
    """What ``iristac live`` opens: ``source`` (an index, device, URL, file or camera *name*,
    :func:`pipeline.capture.camera_names.resolve_camera_source`), by default the profile's
    camera name; with a profile, wrapped in a :class:`ProfileCamera`.

    Returns an OpenCV source (int or str) without a profile, a :class:`ProfileCamera` with one.
    """
    from pipeline.capture.camera_names import BY_ID_DIR, resolve_camera_source

    prof = None if profile is None else load_profile(profile)
    if source is None:
        if prof is None or not prof.camera:
            raise UserError("live: give --camera SOURCE (or a --profile that names its camera)")
        source = prof.camera
    resolved = resolve_camera_source(source, by_id_dir or BY_ID_DIR)
    if prof is None:
        return resolved
    from pipeline.capture.camera import OpenCVCamera

    return ProfileCamera(OpenCVCamera(resolved), prof)
