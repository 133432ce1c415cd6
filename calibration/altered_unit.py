"""An "altered unit": a copy of one sensor's frames as another unit of the same model would record them.

A second unit of a sensor model differs from the first in its camera (another resolution,
mounted turned, a stream larger than the gel) and its LEDs (another brightness per colour).
:func:`make_altered_unit` makes such a copy of a folder of frames (or of an array of frames)
and writes the sensor profile that maps it back to the first unit's canonical image
(:class:`pipeline.capture.sensor_profiles.SensorProfile`: ``crop``, ``rotate``, ``resolution``;
its :meth:`~pipeline.capture.sensor_profiles.SensorProfile.to_image` undoes the geometry).
The colour gain is what the profile cannot undo: a calibration of the first unit meets it
as a new unit's light.

What is done to each canonical frame ``(H, W, C)``, in this order (:func:`alter_frame`):

1. resized to ``size`` (width, height of the canonical image at the new camera's resolution);
2. turned ``rotate`` degrees clockwise (the profile turns it back counter-clockwise, as its
   ``rotate`` says);
3. framed by ``border`` pixels ``(left, top, right, bottom)`` of a dark housing (the profile's
   ``crop`` cuts them off);
4. each channel multiplied by ``gain`` (in the frames' channel order: BGR for files OpenCV reads),
   rounded and clipped to the dtype's range.

Used to measure a calibration on "another unit" when only one unit's frames are at hand
(``iristac bench calibration --shipped``) and to test ``calibrate --prior``.

Examples
--------
>>> frames = np.full((2, 640, 480, 3), 100, np.uint8)        # two DIGIT images (portrait)
>>> alt = Alteration(size=(360, 480), rotate=90, border=(3, 2, 1, 4), gain=(0.9, 1.0, 1.1))
>>> stream, profile = alter_frames(frames, alt, base_profile="digit")
>>> stream.shape                                # 360 x 480 turned to landscape, plus the border
(2, 366, 484, 3)
>>> profile["crop"], profile["rotate"], profile["stream"]
({'x': 3, 'y': 2, 'width': 480, 'height': 360}, 90, {'width': 484, 'height': 366})
>>> back = load_profile_dict(profile).to_image(stream[0])
>>> back.shape, int(back[32, 24, 0]), int(back[32, 24, 2])
((640, 480, 3), 90, 110)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError

__all__ = ["Alteration", "AlteredUnit", "alter_frame", "alter_frames", "make_altered_unit", "load_profile_dict",
           "HOUSING_LEVEL"]

#: Grey level of the border around the gel (the sensor's housing), as a fraction of full scale.
HOUSING_LEVEL = 0.08


@dataclass(frozen=True)
class Alteration:
    """How the altered unit differs (see the module docstring).

    ``size``: ``(width, height)`` of the canonical image at the new camera (before turning);
    ``rotate``: degrees (0, 90, 180, 270) the profile turns the stream counter-clockwise;
    ``border``: ``(left, top, right, bottom)`` stream pixels around the gel;
    ``gain``: one factor per channel, in the frames' channel order."""

    size: tuple[int, int]
    rotate: int = 0
    border: tuple[int, int, int, int] = (0, 0, 0, 0)
    gain: tuple[float, ...] = (1.0, 1.0, 1.0)

    def __post_init__(self):
        if self.rotate not in (0, 90, 180, 270):
            raise UserError(f"Alteration: rotate must be 0, 90, 180 or 270 degrees, got {self.rotate}")
        if min(self.size) < 8 or min(self.border) < 0 or min(self.gain) <= 0:
            raise UserError(f"Alteration: size at least 8 x 8, border >= 0 and gains > 0 (got {self})")

    @classmethod
    def from_seed(cls, seed: int, canonical: tuple[int, int]) -> "Alteration":
        """A random alteration of a ``canonical (width, height)`` image: scale 0.5-0.9, any
        turn but none, a border of 0-40 px on each side, gains 0.8-1.15.

        >>> a = Alteration.from_seed(3, (480, 640))
        >>> a == Alteration.from_seed(3, (480, 640)), a.rotate in (90, 180, 270)
        (True, True)
        """
        rng = np.random.default_rng(seed)
        scale = float(rng.uniform(0.5, 0.9))
        size = (max(8, int(round(canonical[0] * scale))), max(8, int(round(canonical[1] * scale))))
        return cls(size=size, rotate=int(rng.choice([90, 180, 270])),
                   border=tuple(int(v) for v in rng.integers(0, 41, 4)),
                   gain=tuple(round(float(v), 3) for v in rng.uniform(0.8, 1.15, 3)))

    def describe(self) -> str:
        """One line for reports.

        >>> Alteration((360, 480), 270, (10, 0, 10, 0), (0.85, 1.1, 0.95)).describe()
        '360 x 480 px, turned 270 deg, border (10, 0, 10, 0) px, colour gain 0.85 / 1.1 / 0.95'
        """
        return (f"{self.size[0]} x {self.size[1]} px, turned {self.rotate} deg, border {tuple(self.border)} px, "
                f"colour gain {' / '.join(f'{g:g}' for g in self.gain)}")


def alter_frame(frame: np.ndarray, alt: Alteration) -> np.ndarray:
    """One canonical frame ``(H, W, C)`` as the altered unit's camera streams it."""
    import cv2

    f = np.asarray(frame)
    if f.shape[-1] != len(alt.gain):
        raise UserError(f"alter_frame: {f.shape[-1]} channel(s) but {len(alt.gain)} gains")
    shrink = alt.size[0] * alt.size[1] < f.shape[0] * f.shape[1]
    out = cv2.resize(np.ascontiguousarray(f), tuple(int(v) for v in alt.size),
                     interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    out = out.reshape(out.shape[:2] + (f.shape[-1],))
    out = np.rot90(out, k=-(alt.rotate // 90))
    top_value = float(np.iinfo(f.dtype).max) if np.issubdtype(f.dtype, np.integer) else 1.0
    left, top, right, bottom = alt.border
    h, w = out.shape[:2]
    framed = np.full((top + h + bottom, left + w + right, f.shape[-1]), HOUSING_LEVEL * top_value, np.float64)
    framed[top:top + h, left:left + w] = out
    framed *= np.asarray(alt.gain, np.float64)
    if np.issubdtype(f.dtype, np.integer):
        framed = np.clip(np.rint(framed), 0, top_value)
    return framed.astype(f.dtype)


def alter_frames(frames: np.ndarray, alt: Alteration, base_profile="digit",
                 name: str | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """``(stream frames (N, H', W', C), profile dict)``: canonical frames ``(N, H, W, C)`` as the
    altered unit streams them, and the profile (the base profile's keys, with ``stream``,
    ``crop`` and ``rotate`` of the alteration) that maps them back to the canonical size."""
    from pipeline.capture.sensor_profiles import load_profile

    base = load_profile(base_profile)
    frames = np.asarray(frames)
    if frames.shape[1:3] != (base.resolution[1], base.resolution[0]):
        raise UserError(f"alter_frames: frames are {frames.shape[2]} x {frames.shape[1]} px, sensor profile "
                        f"{base.name!r} is for {base.resolution[0]} x {base.resolution[1]}")
    stream = np.stack([alter_frame(f, alt) for f in frames])
    left, top, right, bottom = alt.border
    turned = alt.size if alt.rotate in (0, 180) else alt.size[::-1]
    profile: dict[str, Any] = {
        "name": name or f"{base.name}-altered",
        "make": f"{base.make} (an altered copy: {alt.describe()})",
        "stream": {"width": int(stream.shape[2]), "height": int(stream.shape[1])},
        "crop": {"x": int(left), "y": int(top), "width": int(turned[0]), "height": int(turned[1])},
        "rotate": int(alt.rotate),
        "resolution": {"width": base.resolution[0], "height": base.resolution[1]},
        "mm_per_px": base.mm_per_px, "ball_radius_mm": base.ball_radius_mm,
    }
    for key in ("mode", "calibration_drift", "calibration_mlp_members"):
        if getattr(base, key) is not None:
            profile[key] = getattr(base, key)
    profile["notes"] = (f"Made by calibration.altered_unit from frames of sensor profile {base.name!r}: "
                        f"{alt.describe()}.")
    return stream, profile


def load_profile_dict(profile: dict[str, Any], where: str = "altered unit"):
    """A :class:`pipeline.capture.sensor_profiles.SensorProfile` from a profile dict (validated as a file is)."""
    import tempfile

    import yaml

    from pipeline.capture.sensor_profiles import load_profile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{profile.get('name', where)}.yaml"
        path.write_text(yaml.safe_dump(profile, sort_keys=False), encoding="utf-8")
        return load_profile(path)


@dataclass(frozen=True)
class AlteredUnit:
    """What :func:`make_altered_unit` wrote: the ``frames`` folder, the ``profile`` file and the
    ``alteration``."""

    frames: Path
    profile: Path
    alteration: Alteration

    def to_dict(self) -> dict[str, Any]:
        return {"frames": str(self.frames), "profile": str(self.profile), "alteration": asdict(self.alteration)}


def make_altered_unit(source, out, *, seed: int = 0, alteration: Alteration | None = None,
                      base_profile="digit", names: list[str] | None = None, suffix: str = ".png") -> AlteredUnit:
    """Write an altered copy of ``source`` under ``out`` and the profile that maps it back.

    Parameters
    ----------
    source : folder or array
        A folder of image files (every frame of the base profile's resolution, read as OpenCV
        reads them, BGR) or frames ``(N, H, W, C)``.
    out : path
        Folder to write: ``out/frames/`` (one file per frame, the source's names with
        ``suffix``; ``frame_<i>`` for an array) and ``out/<profile name>.yaml``.
    seed, alteration
        The alteration: given, else :meth:`Alteration.from_seed`.
    base_profile : str, path or SensorProfile
        The sensor whose canonical image the frames are (default the DIGIT's).
    names : list of str, optional
        File names of an array's frames (without suffix).
    suffix : str
        ``.png`` (lossless, default) or ``.jpg`` (quality 95, as a camera's JPEG stream).

    Returns
    -------
    AlteredUnit
        ``iristac import images OUT/frames --profile OUT/<name>.yaml`` imports it as the base
        sensor's images.
    """
    import cv2
    import yaml

    from calibration.image_import import IMAGE_SUFFIXES
    from pipeline.capture.sensor_profiles import load_profile

    base = load_profile(base_profile)
    if isinstance(source, (str, Path)):
        files = sorted(p for p in Path(source).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise UserError(f"{source}: no image files")
        read = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in files]
        bad = [p for p, f in zip(files, read) if f is None or f.ndim != 3]
        if bad:
            raise UserError(f"{bad[0]}: not a colour image OpenCV can read")
        frames = np.stack(read)
        names = [p.stem for p in files]
    else:
        frames = np.asarray(source)
        names = names or [f"frame_{i}" for i in range(len(frames))]
    alt = alteration or Alteration.from_seed(seed, base.resolution)
    stream, profile = alter_frames(frames, alt, base, name=f"{base.name}-altered-{seed}" if alteration is None
                                   else f"{base.name}-altered")
    out = Path(out)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if suffix.lower() in (".jpg", ".jpeg") else []
    for n, f in zip(names, stream):
        if not cv2.imwrite(str(out / "frames" / f"{n}{suffix}"), f, params):
            raise UserError(f"{out / 'frames' / (n + suffix)}: could not write")
    path = out / f"{profile['name']}.yaml"
    path.write_text(yaml.safe_dump(profile, sort_keys=False), encoding="utf-8")
    load_profile(path)  # the file is a valid profile
    return AlteredUnit(frames=out / "frames", profile=path, alteration=alt)
