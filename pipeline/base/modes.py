"""Lighting modes: named sets of LED patterns, stored as data files (``pipeline/base/modes/*.yaml``).

A mode is a list of frames; each frame drives the ``L`` LEDs with an ``(L, 3)`` matrix of RGB
levels in ``[0, 1]`` (``W_p[i, j]`` in ``docs/design.md``) and has a global brightness. The built-in
modes follow the paper's Fig. 5:

``point``
    One LED at a time, white (24 frames).
``monochromatic``
    Three white sectors of 8 LEDs in sequence (3 frames).
``trichromatic``
    The same three sectors lit red, green and blue in one frame (GelSight style).
``multicolour``
    Every LED a blend: a colour wheel with weights ``(1 + cos(phi_i - phi_j)) / 2`` around the
    ring, channel ``j`` centred on sector ``j`` (1 frame).

A user mode is any YAML/JSON file with the same layout (schema ``data_schemas/configs/mode.json``)::

    name: my-mode
    leds: 24
    frames:
      - name: left
        brightness: 0.8
        drive: [[1, 1, 1], [0, 0, 0], ...]   # 24 rows of [R, G, B]

LED ``i`` sits at azimuth ``15 i`` degrees from optical ``+x`` toward optical ``+y``
(:func:`sim.point_source.ring_geometry`). In an image displayed with row 0 at the top, LED 0
lights from the right (larger columns) and LED 6 from the bottom (larger rows), so the index
runs clockwise on screen (:mod:`pipeline.base.frames`: optical ``y`` grows with the row).

Examples
--------
>>> mode = load_mode("trichromatic")
>>> mode.name, len(mode.frames), mode_drive(mode).shape, mode_brightness(mode).tolist()
('trichromatic', 1, (1, 24, 3), [1.0])
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.registry import MODES_DIR, list_modes

__all__ = ["ModeFrame", "LightingMode", "load_mode", "read_config_file", "list_modes", "mode_drive", "mode_brightness", "save_mode", "describe_modes",
           "MODES_DIR"]


class ModeFrame(NamedTuple):
    """One pattern of a mode: ``(name, drive (L, 3), brightness)``."""

    name: str
    drive: np.ndarray
    brightness: float


@dataclass
class LightingMode:
    """A lighting mode: its name, its patterns (frames), description and the file it came from.

    The one pattern type of the project: the renderer, the capture plan, calibration and
    the uniformity report all take a ``LightingMode`` (:func:`load_mode` reads one from a
    file, :meth:`from_arrays` builds one from arrays).

    Attributes
    ----------
    name : str
    frames : list of ModeFrame, length P
        Each pattern's name, RGB drive ``(L, 3)`` in [0, 1] and brightness in [0, 1].
    description, source : str

    Raises
    ------
    UserError
        No patterns, patterns of different LED counts, duplicate names, or values outside
        [0, 1] (naming the mode and the pattern).
    """

    name: str
    frames: list[ModeFrame]
    description: str = ""
    source: str = ""

    def __post_init__(self) -> None:
        self.frames = [ModeFrame(str(f[0]), np.asarray(f[1], dtype=np.float64), float(f[2])) for f in self.frames]
        if not self.frames:
            raise UserError(f"mode {self.name!r}: no patterns")
        leds = self.frames[0].drive.shape[0] if self.frames[0].drive.ndim == 2 else -1
        for f in self.frames:
            if f.drive.ndim != 2 or f.drive.shape != (leds, 3):
                raise UserError(f"mode {self.name!r}, pattern {f.name!r}: drive must have shape (L, 3) with one L "
                                f"for every pattern, got {f.drive.shape}")
            if not np.all(np.isfinite(f.drive)) or f.drive.min(initial=0) < 0 or f.drive.max(initial=0) > 1:
                raise UserError(f"mode {self.name!r}, pattern {f.name!r}: drive values must be finite and in [0, 1]")
            if not (np.isfinite(f.brightness) and 0 <= f.brightness <= 1):
                raise UserError(f"mode {self.name!r}, pattern {f.name!r}: brightness must be in [0, 1], "
                                f"got {f.brightness}")
        if len(set(self.pattern_names)) != len(self.frames):
            raise UserError(f"mode {self.name!r}: pattern names must be unique, got {self.pattern_names}")

    @classmethod
    def from_arrays(cls, name: str, names: Sequence[str], drive, brightness, description: str = "",
                    source: str = "") -> "LightingMode":
        """A mode from ``names`` (P), ``drive (P, L, 3)`` and ``brightness (P,)``.

        Examples
        --------
        >>> m = LightingMode.from_arrays("two", ["a", "b"], np.ones((2, 24, 3)), [1.0, 0.5])
        >>> m.drive.shape, m.brightness.tolist(), m.num_leds
        ((2, 24, 3), [1.0, 0.5], 24)
        """
        names = [str(n) for n in names]
        d = np.asarray(drive, dtype=np.float64)
        b = np.asarray(brightness, dtype=np.float64).reshape(-1)
        p = len(names)
        if d.ndim != 3 or d.shape[0] != p or d.shape[2] != 3:
            raise UserError(f"mode {name!r}: drive must have shape (P={p}, L, 3), got {d.shape}")
        if b.shape != (p,):
            raise UserError(f"mode {name!r}: brightness must have shape (P={p},), got {b.shape}")
        return cls(str(name), [ModeFrame(n, d[i], float(b[i])) for i, n in enumerate(names)], description, source)

    @property
    def num_leds(self) -> int:
        """L, the LEDs each pattern drives."""
        return int(self.frames[0].drive.shape[0])

    @property
    def pattern_names(self) -> list[str]:
        """The P pattern names, in order."""
        return [f.name for f in self.frames]

    @cached_property
    def drive(self) -> np.ndarray:
        """``(P, L, 3)`` float64 RGB drive per pattern and LED."""
        return np.stack([f.drive for f in self.frames])

    @cached_property
    def brightness(self) -> np.ndarray:
        """``(P,)`` float64 global brightness per pattern."""
        return np.array([f.brightness for f in self.frames], dtype=np.float64)


def read_config_file(kind: str, path) -> Any:
    """A YAML config file, validated against ``data_schemas/configs/<kind>.json``
    (:func:`data_schemas.load_config_file`; its errors, naming the file and the key, as UserError)."""
    from data_schemas import SchemaError, load_config_file

    try:
        return load_config_file(kind, path)
    except SchemaError as exc:
        raise UserError(str(exc)) from None


def load_mode(name_or_path) -> LightingMode:
    """Load a built-in mode by name, or a user mode from a YAML/JSON file.

    Parameters
    ----------
    name_or_path : str or Path
        A name from :func:`list_modes` or the path of a mode file.

    Raises
    ------
    pipeline.base.errors.UserError
        Unknown name, unreadable file, or a file that breaks the schema (the message names
        the file and the key, e.g. ``frames/2/drive``).
    """
    if isinstance(name_or_path, LightingMode):
        return name_or_path
    s = str(name_or_path)
    path = Path(s)
    if not (path.suffix.lower() in (".yaml", ".yml", ".json") or path.exists()):
        path = MODES_DIR / f"{s}.yaml"
        if not path.is_file():
            raise UserError(f"unknown lighting mode {s!r}: not a file and not one of {', '.join(list_modes())}")
    obj = read_config_file("mode", path)
    leds = int(obj["leds"])
    frames = []
    seen = set()
    for k, fr in enumerate(obj["frames"]):
        drive = np.asarray(fr["drive"], dtype=np.float64)
        if drive.shape != (leds, 3):
            raise UserError(f"{path}: frames/{k}/drive: expected {leds} rows of [R, G, B] (leds: {leds}), "
                            f"got shape {drive.shape}")
        if fr["name"] in seen:
            raise UserError(f"{path}: frames/{k}/name: duplicate frame name {fr['name']!r}")
        seen.add(fr["name"])
        frames.append(ModeFrame(str(fr["name"]), drive, float(fr.get("brightness", 1.0))))
    return LightingMode(str(obj["name"]), frames, str(obj.get("description", "")), str(path))


def mode_drive(mode) -> np.ndarray:
    """Drive matrices ``(P, L, 3)`` (float32) of a mode (a LightingMode, name or path)."""
    mode = load_mode(mode)
    return np.stack([f.drive for f in mode.frames]).astype(np.float32)


def mode_brightness(mode) -> np.ndarray:
    """Global brightness ``(P,)`` (float32) of each frame of a mode."""
    mode = load_mode(mode)
    return np.array([f.brightness for f in mode.frames], dtype=np.float32)


def save_mode(mode: LightingMode, path) -> Path:
    """Write a mode as YAML (one LED row per line) that :func:`load_mode` reads back exactly.

    Examples
    --------
    >>> import tempfile, os
    >>> d = np.zeros((24, 3)); d[5] = [1.0, 0.5, 0.0]
    >>> p = save_mode(LightingMode("one", [ModeFrame("led5", d, 0.75)]), os.path.join(tempfile.mkdtemp(), "one.yaml"))
    >>> m = load_mode(p)
    >>> m.frames[0].brightness, m.frames[0].drive[5].tolist()
    (0.75, [1.0, 0.5, 0.0])
    """
    path = Path(path)
    lines = [f"name: {mode.name}"]
    if mode.description:
        lines.append(f"description: {_yaml_str(mode.description)}")
    lines += [f"leds: {mode.num_leds}", "frames:"]
    for f in mode.frames:
        lines += [f"  - name: {_yaml_str(f.name)}", f"    brightness: {float(f.brightness)!r}", "    drive:"]
        for i, row in enumerate(np.asarray(f.drive, dtype=np.float64)):
            vals = ", ".join(repr(float(v)) for v in row)
            lines.append(f"      - [{vals}]  # LED {i}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _yaml_str(s: str) -> str:
    import json

    return json.dumps(s)  # a JSON string is a valid YAML scalar


def describe_modes(names: list | None = None) -> list[dict]:
    """One summary per mode (default: the built-in ones): what ``iristac sim modes`` prints.

    Examples
    --------
    >>> [d["frames"] for d in describe_modes(["point", "trichromatic"])]
    [24, 1]
    """
    out = []
    for n in names if names is not None else list_modes():
        m = load_mode(n)
        out.append({"name": m.name, "frames": len(m.frames), "leds": m.num_leds, "patterns": m.pattern_names,
                    "description": m.description, "file": m.source})
    return out
