"""The typed view of a ``capture`` record, and the functions that write a capture file.

The on-disk layout is the ``capture`` stage of ``docs/developing.md`` (``frames (K, P, H, W, C)``,
``reference (P, H, W, C)``, optional ``dark (H, W, C)``, ``drive (P, L, 3)``,
``brightness (P,)``, attribute ``mm_per_px`` ...). Hand labels travel as optional datasets
``labels/center_xy (K, 2)`` and ``labels/radius_px (K,)`` (and ``labels/rejected (K,)``: presses
a person rejected); calibration fits to them only when asked (``circles="labels"``).

Every capture file, whoever makes it (the renderer, the importers, calibration's synthetic
captures), is written by :func:`write_capture`, from a :class:`Capture` or a ``capture``
:class:`~pipeline.base.store.Record`; :func:`write_capture_labels` replaces only its hand
labels (the labeller, ``iristac label``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError

__all__ = ["Capture", "read_capture", "capture_from_record", "write_capture", "write_capture_labels",
           "CAPTURE_WIDE_TRUTH"]

#: ``truth/*`` entries of the whole capture (not one per press): kept whole by :meth:`Capture.select`.
CAPTURE_WIDE_TRUTH = frozenset({"albedo", "markers"})


@dataclass
class Capture:
    """A sphere-indentation capture.

    Attributes
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        K presses under P patterns, camera values (uint8/uint16/float).
    reference : ndarray, shape (P, H, W, C)
        No-contact frames, one per pattern.
    drive : ndarray, shape (P, L, 3)
        LED drive per pattern.
    brightness : ndarray, shape (P,)
    mm_per_px : float or None
    dark : ndarray, shape (H, W, C), optional
    labels : dict, optional
        ``{"center_xy": (K, 2), "radius_px": (K,)}`` hand labels (NaN: not labelled), and
        ``"rejected": (K,)`` bool where a person rejected the press (``iristac label``).
    truth : dict, optional
        ``{"height": (K, H, W), "normals": (K, H, W, 3)}`` for rendered captures; virtual
        sensors (:mod:`sim.virtual_sensor`) add ``contact (K, H, W)``, ``center_xy (K, 2)``,
        ``radius_px (K,)``, ``drift_*`` per press and ``markers (H, W)``. Entries named in
        :data:`CAPTURE_WIDE_TRUTH` belong to the whole capture, every other one to each press.
    markers : ndarray, shape (H, W), bool, optional
        Printed gel markers (:mod:`calibration.markers`): filled in before normals are solved,
        left out of calibration samples, False in validity masks.
    meta : dict
        Other attributes (``source``, ``pattern_names``, ``bit_depth`` ...).
    """

    frames: np.ndarray
    reference: np.ndarray
    drive: np.ndarray
    brightness: np.ndarray
    mm_per_px: float | None = None
    dark: np.ndarray | None = None
    labels: dict[str, np.ndarray] | None = None
    truth: dict[str, np.ndarray] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    markers: np.ndarray | None = None

    def __post_init__(self):
        f = np.asarray(self.frames)
        if f.ndim != 5:
            raise UserError(f"capture: frames must have shape (K, P, H, W, C), got {f.shape}")
        r = np.asarray(self.reference)
        if r.shape != f.shape[1:]:
            raise UserError(f"capture: reference must have shape {f.shape[1:]} (P, H, W, C), got {r.shape}")
        d = np.asarray(self.drive)
        if d.ndim != 3 or d.shape[0] != f.shape[1] or d.shape[2] != 3:
            raise UserError(f"capture: drive must have shape ({f.shape[1]}, L, 3) (P, L, 3), got {d.shape}")
        b = np.asarray(self.brightness)
        if b.shape != (f.shape[1],):
            raise UserError(f"capture: brightness must have shape ({f.shape[1]},) (P,), got {b.shape}")
        if self.dark is not None and np.asarray(self.dark).shape != f.shape[2:]:
            raise UserError(f"capture: dark must have shape {f.shape[2:]} (H, W, C), got {np.asarray(self.dark).shape}")
        if self.markers is not None:
            if np.asarray(self.markers).shape != f.shape[2:4]:
                raise UserError(f"capture: markers must have shape {f.shape[2:4]} (H, W), got "
                                f"{np.asarray(self.markers).shape}")
            self.markers = np.asarray(self.markers).astype(bool)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.frames.shape[2]), int(self.frames.shape[3])

    def select(self, presses) -> "Capture":
        """The capture restricted to some presses (index array or slice), reference and all else shared.

        Examples
        --------
        >>> cap = Capture(np.zeros((5, 1, 2, 2, 3)), np.zeros((1, 2, 2, 3)), np.ones((1, 1, 3)), np.ones(1))
        >>> cap.select(slice(0, 3)).frames.shape
        (3, 1, 2, 2, 3)
        """
        idx = np.arange(self.frames.shape[0])[presses]
        sub = {k: np.asarray(v)[idx] for k, v in (self.labels or {}).items()} or None
        truth = {k: (np.asarray(v)[idx] if np.asarray(v).ndim and k not in CAPTURE_WIDE_TRUTH else v)
                 for k, v in (self.truth or {}).items()} or None
        meta = dict(self.meta)
        if isinstance(meta.get("frame_names"), list) and len(meta["frame_names"]) == self.frames.shape[0]:
            meta["frame_names"] = [meta["frame_names"][i] for i in idx]
        return Capture(frames=np.asarray(self.frames)[idx], reference=self.reference, drive=self.drive,
                       brightness=self.brightness, mm_per_px=self.mm_per_px, dark=self.dark, labels=sub, truth=truth,
                       meta=meta, markers=self.markers)

    def linear(self) -> tuple[np.ndarray, np.ndarray]:
        """Frames ``(K, P, H, W, C)`` and reference ``(P, H, W, C)`` as float32, dark level removed."""
        frames = np.asarray(self.frames, dtype=np.float32)
        ref = np.asarray(self.reference, dtype=np.float32)
        if self.dark is not None:
            dark = np.asarray(self.dark, dtype=np.float32)
            frames = frames - dark
            ref = ref - dark
        return frames, ref


_OPTIONAL = {"labels/center_xy", "labels/radius_px", "truth/height", "truth/normals", "truth/albedo", "dark", "markers"}


def write_capture(path: str | Path, cap) -> Path:
    """Write a capture atomically, schema-checked, as a ``capture`` file (see :mod:`pipeline.base.store`).

    Parameters
    ----------
    path : path-like
    cap : Capture or Record
        A :class:`Capture`, or a ``capture`` :class:`~pipeline.base.store.Record` (e.g. from
        :func:`sim.rendered_capture.render_capture`).

    Returns
    -------
    Path
        The path written.
    """
    from pipeline.base.store import Record, write_record

    if isinstance(cap, Record):
        if cap.schema != "capture":
            raise UserError(f"{path}: expected a 'capture' record, got {cap.schema!r}")
        return write_record(path, cap)
    data: dict[str, np.ndarray] = {
        "frames": np.asarray(cap.frames),
        "reference": np.asarray(cap.reference),
        "drive": np.asarray(cap.drive, dtype=np.float32),
        "brightness": np.asarray(cap.brightness, dtype=np.float32),
    }
    if cap.dark is not None:
        data["dark"] = np.asarray(cap.dark)
    if cap.markers is not None:
        data["markers"] = np.asarray(cap.markers).astype(np.uint8)
    for group, arrays in (("labels", cap.labels), ("truth", cap.truth)):
        for k, v in (arrays or {}).items():
            data[f"{group}/{k}"] = np.asarray(v)
    meta = dict(cap.meta)
    if cap.mm_per_px is not None:
        meta["mm_per_px"] = float(cap.mm_per_px)
    return write_record(path, Record(schema="capture", data=data, meta=meta))


def write_capture_labels(path: str | Path, center_xy, radius_px, rejected=None) -> Path:
    """Replace a capture file's hand labels, atomically, leaving everything else as it is.

    Parameters
    ----------
    path : path-like
        An existing capture file.
    center_xy : array_like, shape (K, 2)
        Labelled centres (x = column, y = row) in pixels; NaN for a press without a label.
    radius_px : array_like, shape (K,)
        Labelled radii in pixels; NaN for a press without a label.
    rejected : array_like of bool, shape (K,), optional
        Presses a person rejected (``labels/rejected``); None removes the dataset.

    The file is copied, changed and renamed into place
    (:func:`pipeline.base.store.replace_datasets`): a crash leaves the old file or the new one.
    """
    from pipeline.base.store import describe_file, replace_datasets

    description, _ = describe_file(path)
    frames = description["datasets"].get("frames")
    if frames is None:
        raise UserError(f"{path}: not a capture (no 'frames' dataset)")
    k = int(frames["shape"][0])
    c = np.asarray(center_xy, np.float32)
    r = np.asarray(radius_px, np.float32)
    if c.shape != (k, 2) or r.shape != (k,):
        raise UserError(f"{path}: labels must be center_xy ({k}, 2) and radius_px ({k},) for its {k} presses, got "
                        f"{c.shape} and {r.shape}")
    updates: dict[str, Any] = {"labels/center_xy": c, "labels/radius_px": r, "labels/rejected": None}
    if rejected is not None:
        rej = np.asarray(rejected, bool)
        if rej.shape != (k,):
            raise UserError(f"{path}: labels/rejected must have shape ({k},), got {rej.shape}")
        updates["labels/rejected"] = rej
    return replace_datasets(path, updates)


def read_capture(path: str | Path) -> Capture:
    """Read a ``capture`` record written by :func:`write_capture` or the capture stage."""
    from pipeline.base.store import read_record

    if not Path(path).is_file():
        raise UserError(f"{path}: no such file (expected a 'capture' HDF5 record)")
    return capture_from_record(read_record(path, schema="capture"))


def capture_from_record(rec) -> Capture:
    """The :class:`Capture` view of a ``capture`` :class:`~pipeline.base.store.Record`
    (read from a file or made in memory); errors name the record's file."""
    where = rec.path if rec.path is not None else "capture"
    data, meta = dict(rec.data), dict(rec.meta)
    for key in ("frames", "reference"):
        if key not in data:
            raise UserError(f"{where}: capture has no dataset '{key}' (expected (K, P, H, W, C) frames and "
                            "(P, H, W, C) reference)")
    frames = data["frames"]
    p = frames.shape[1] if frames.ndim == 5 else 0
    drive = data.get("drive")
    if drive is None:
        drive = np.ones((p, 1, 3), dtype=np.float32)
    brightness = data.get("brightness", np.ones(p, dtype=np.float32))
    labels = {k.split("/", 1)[1]: v for k, v in data.items() if k.startswith("labels/")} or None
    truth = {k.split("/", 1)[1]: v for k, v in data.items() if k.startswith("truth/")} or None
    mm = meta.pop("mm_per_px", None)
    try:
        return Capture(frames=frames, reference=data["reference"], drive=drive, brightness=brightness,
                       mm_per_px=None if mm is None else float(mm), dark=data.get("dark"), labels=labels,
                       truth=truth, meta=meta, markers=data.get("markers"))
    except UserError as exc:
        if rec.path is None:
            raise
        raise UserError(f"{rec.path}: {exc}") from None
