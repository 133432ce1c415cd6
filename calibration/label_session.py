"""Hand-labelling one capture's contact circles: the state behind ``iristac label`` (no web code here).

A :class:`LabelSession` opens a capture file, detects each press's circle when first asked
(:func:`calibration.detect.detect_contacts`), and holds the person's decision per press:

- a **label**: a circle ``(x, y, radius_px)`` (x = column, y = row, pixels) the person
  accepted, moved or resized;
- **rejected**: no usable contact in this press;
- undecided.

Every decision is saved as it is made, before the call returns: into the capture itself
(``labels/center_xy``, ``labels/radius_px``, NaN where undecided or rejected, and
``labels/rejected``; :func:`pipeline.base.capture.write_capture_labels`: copy, change,
rename, so the capture is never half-written) and into a CSV beside it (``name,x,y,radius_px``,
``name,,,`` for a rejected press, undecided presses as ``#`` comment lines: the format
``iristac import images --labels`` reads; written to a temporary file and renamed). Opening
the capture again shows what was saved (the session resumes); labels that came with the
capture (an import's) are shown the same way.

Examples
--------
>>> import tempfile, os
>>> from sim.virtual_sensor import random_sensor, write_sensor_capture
>>> path = os.path.join(tempfile.mkdtemp(), "cap.h5")
>>> _ = write_sensor_capture(path, random_sensor(1, shape=(48, 64), num_presses=2, effects="none"))
>>> s = LabelSession(path)
>>> s.set_label(0, 30.0, 20.5, 9.0)["label"]
{'x': 30.0, 'y': 20.5, 'radius_px': 9.0}
>>> _ = s.reject(1)
>>> [p["status"] for p in LabelSession(path).presses()]          # reopened: resumed
['labelled', 'rejected']
>>> open(s.csv_path).read().splitlines()[1:]
['press0,30.000,20.500,9.000', 'press1,,,']
"""

from __future__ import annotations

import os
import secrets
import threading
from pathlib import Path
from typing import Any

import numpy as np

from calibration.detect import Circle, DetectOptions, detect_contacts
from pipeline.base.capture import read_capture, write_capture_labels
from pipeline.base.errors import UserError

__all__ = ["LabelSession", "write_labels_csv", "display_image", "display_difference"]


def write_labels_csv(path, names, center_xy, radius_px, rejected) -> Path:
    """Write the labels as CSV atomically (temporary file + rename): ``name,x,y,radius_px`` per
    labelled press, ``name,,,`` per rejected one, ``# name: not labelled`` per undecided one.

    Examples
    --------
    >>> import tempfile, os
    >>> p = write_labels_csv(os.path.join(tempfile.mkdtemp(), "l.csv"), ["a", "b", "c"],
    ...                      [[1, 2], [np.nan, np.nan], [np.nan, np.nan]], [3, np.nan, np.nan], [False, True, False])
    >>> open(p).read().splitlines()
    ['name,x,y,radius_px', 'a,1.000,2.000,3.000', 'b,,,', '# c: not labelled']
    """
    path = Path(path)
    lines = ["name,x,y,radius_px"]
    for name, (x, y), r, rej in zip(names, np.asarray(center_xy, float), np.asarray(radius_px, float),
                                    np.asarray(rejected, bool)):
        if "," in name or "\n" in name:
            raise UserError(f"{path}: press name {name!r} cannot be written to a CSV row")
        if rej:
            lines.append(f"{name},,,")
        elif np.isfinite([x, y, r]).all():
            lines.append(f"{name},{x:.3f},{y:.3f},{r:.3f}")
        else:
            lines.append(f"# {name}: not labelled")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write("\n".join(lines) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def display_image(frames: np.ndarray) -> np.ndarray:
    """One press's frames ``(P, H, W, C)`` as an RGB uint8 image to look at (mean over patterns).

    Examples
    --------
    >>> display_image(np.full((2, 3, 4, 1), 1000, np.uint16)).shape
    (3, 4, 3)
    """
    f = np.asarray(frames)
    img = f.astype(np.float32).mean(axis=0)
    if f.dtype != np.uint8:
        top = float(np.percentile(img, 99.9)) or 1.0
        img = img * (255.0 / top)
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    return np.clip(np.round(img[..., :3]), 0, 255).astype(np.uint8)


def display_difference(frames: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The press against the reference as an RGB uint8 image: grey 128 where nothing changed.

    Per channel, summed over patterns, minus its median (a global drift of the light then
    shows as nothing), scaled so the 99.5th percentile of the change spans the range.

    Examples
    --------
    >>> ref = np.full((1, 8, 8, 3), 100.0); f = ref.copy(); f[0, 2:4, 2:4, 0] += 50
    >>> d = display_difference(f, ref)
    >>> int(d[0, 0, 0]), int(d[2, 2, 0]) > 200
    (128, True)
    """
    d = (np.asarray(frames, np.float32) - np.asarray(reference, np.float32)).sum(axis=0)
    d -= np.median(d.reshape(-1, d.shape[-1]), axis=0)
    scale = float(np.percentile(np.abs(d), 99.5)) or 1.0
    if d.shape[-1] == 1:
        d = np.repeat(d, 3, axis=-1)
    return np.clip(np.round(128 + d[..., :3] * (127.0 / scale)), 0, 255).astype(np.uint8)


class LabelSession:
    """One capture being labelled (thread-safe: a web server calls it from several threads).

    Parameters
    ----------
    capture_path : path
        The capture file (labels are saved into it).
    ball_radius_mm : float, optional
        Default: the capture's ``ball_radius_mm`` attribute.
    csv_path : path, optional
        Default: ``CAPTURE.labels.csv`` beside the capture.
    detect_options : calibration.detect.DetectOptions, optional
    """

    def __init__(self, capture_path, *, ball_radius_mm: float | None = None, csv_path=None,
                 detect_options: DetectOptions | None = None):
        self.path = Path(capture_path)
        cap = read_capture(self.path)
        self.capture = cap
        k = int(cap.frames.shape[0])
        if k == 0:
            raise UserError(f"{self.path}: the capture has no presses to label")
        if cap.mm_per_px is None:
            raise UserError(f"{self.path}: no mm_per_px attribute (needed to scale the ball)")
        ball = ball_radius_mm if ball_radius_mm is not None else cap.meta.get("ball_radius_mm")
        if ball is None or not float(ball) > 0:
            raise UserError(f"{self.path}: no ball_radius_mm attribute; give the pressed ball's radius (--ball-radius "
                            f"MM), got {ball!r}")
        self.ball_radius_mm = float(ball)
        self.ball_radius_px = self.ball_radius_mm / float(cap.mm_per_px)
        names = cap.meta.get("frame_names")
        self.names = [str(n) for n in names] if isinstance(names, list) and len(names) == k else \
            [f"press{i}" for i in range(k)]
        self.csv_path = Path(csv_path) if csv_path is not None else self.path.with_name(self.path.stem + ".labels.csv")
        lab = cap.labels or {}
        self._center = np.full((k, 2), np.nan)
        self._radius = np.full(k, np.nan)
        self._rejected = np.zeros(k, bool)
        if "center_xy" in lab and "radius_px" in lab:
            c, r = np.asarray(lab["center_xy"], float), np.asarray(lab["radius_px"], float)
            if c.shape == (k, 2) and r.shape == (k,):
                self._center, self._radius = c.copy(), r.copy()
        if "rejected" in lab and np.shape(lab["rejected"]) == (k,):
            self._rejected = np.asarray(lab["rejected"], bool).copy()
        self._detected: list[Circle | None] = [None] * k
        self._options = detect_options
        self._linear = None
        self._lock = threading.RLock()
        self.saves = 0

    @property
    def num_presses(self) -> int:
        return len(self.names)

    @property
    def shape(self) -> tuple[int, int]:
        return self.capture.shape

    def _check(self, k) -> int:
        k = int(k)
        if not 0 <= k < self.num_presses:
            raise UserError(f"{self.path}: no press {k} (the capture has {self.num_presses}: "
                            f"0..{self.num_presses - 1})")
        return k

    def _linear_frames(self):
        """Linear frames and reference, markers filled in (what calibration detects on)."""
        if self._linear is None:
            frames, ref = self.capture.linear()
            if self.capture.markers is not None:
                from pipeline.normals.prepare import fill_markers

                frames, ref = fill_markers(frames, self.capture.markers), fill_markers(ref, self.capture.markers)
            self._linear = (frames, ref)
        return self._linear

    def detected(self, k: int) -> Circle:
        """Press ``k``'s detected circle (detected on first use, then kept)."""
        k = self._check(k)
        with self._lock:
            if self._detected[k] is None:
                frames, ref = self._linear_frames()
                self._detected[k] = detect_contacts(frames[k:k + 1], ref, self.ball_radius_px, self._options,
                                                     exclude=self.capture.markers)[0]
            return self._detected[k]

    def press(self, k: int, detect: bool = True) -> dict[str, Any]:
        """Press ``k`` as JSON-able dict: ``index``, ``name``, ``status`` (labelled / rejected /
        undecided), ``label`` (``x``, ``y``, ``radius_px`` or None), ``detected`` (the circle's
        ``x``, ``y``, ``radius_px``, ``contact_radius_px``, ``accepted``, ``reason``; only with ``detect``)."""
        k = self._check(k)
        with self._lock:
            c, r, rej = self._center[k], self._radius[k], bool(self._rejected[k])
            has = bool(np.isfinite(c).all() and np.isfinite(r))
            out: dict[str, Any] = {
                "index": k, "name": self.names[k],
                "status": "rejected" if rej else "labelled" if has else "undecided",
                "label": {"x": float(c[0]), "y": float(c[1]), "radius_px": float(r)} if has and not rej else None,
            }
        if detect:
            d = self.detected(k)
            out["detected"] = {"x": float(d.center_xy[0]), "y": float(d.center_xy[1]), "radius_px": float(d.radius_px),
                               "contact_radius_px": float(d.contact_radius_px), "accepted": bool(d.accepted),
                               "reason": str(d.reason)}
        return out

    def presses(self) -> list[dict[str, Any]]:
        """Every press's state, without detecting (cheap)."""
        return [self.press(k, detect=False) for k in range(self.num_presses)]

    def summary(self) -> dict[str, Any]:
        """``capture``, ``csv``, ``shape`` (H, W), ``ball_radius_px``, ``presses`` (:meth:`presses`),
        ``labelled``, ``rejected``, ``undecided`` counts."""
        ps = self.presses()
        count = {s: sum(p["status"] == s for p in ps) for s in ("labelled", "rejected", "undecided")}
        return {"capture": str(self.path), "csv": str(self.csv_path), "shape": list(self.shape),
                "ball_radius_px": self.ball_radius_px, "presses": ps, **count}

    def set_label(self, k: int, x: float, y: float, radius_px: float) -> dict[str, Any]:
        """Label press ``k`` with a circle (accept, move, resize), saved before returning."""
        k = self._check(k)
        h, w = self.shape
        vals = [float(x), float(y), float(radius_px)]
        if not np.isfinite(vals).all() or not vals[2] > 0:
            raise UserError(f"press {k}: a label needs finite x, y and a positive radius, got {vals}")
        if not (-0.5 <= vals[0] <= w - 0.5 and -0.5 <= vals[1] <= h - 0.5):
            raise UserError(f"press {k}: the centre ({vals[0]:.1f}, {vals[1]:.1f}) is outside the {w} x {h} image")
        if vals[2] > max(h, w):
            raise UserError(f"press {k}: radius {vals[2]:.1f} px is larger than the image")
        with self._lock:
            self._center[k], self._radius[k], self._rejected[k] = vals[:2], vals[2], False
            self._save()
        return self.press(k, detect=False)

    def reject(self, k: int) -> dict[str, Any]:
        """Mark press ``k`` rejected (no usable contact), saved before returning."""
        k = self._check(k)
        with self._lock:
            self._center[k], self._radius[k], self._rejected[k] = np.nan, np.nan, True
            self._save()
        return self.press(k, detect=False)

    def clear(self, k: int) -> dict[str, Any]:
        """Forget the decision on press ``k`` (undecided again), saved before returning."""
        k = self._check(k)
        with self._lock:
            self._center[k], self._radius[k], self._rejected[k] = np.nan, np.nan, False
            self._save()
        return self.press(k, detect=False)

    def _save(self) -> None:
        """Capture first (the labels' home), then the CSV; each replaced atomically."""
        write_capture_labels(self.path, self._center, self._radius, self._rejected)
        write_labels_csv(self.csv_path, self.names, self._center, self._radius, self._rejected)
        self.saves += 1

    def frame_image(self, k: int) -> np.ndarray:
        """Press ``k`` to look at (:func:`display_image`)."""
        return display_image(self.capture.frames[self._check(k)])

    def difference_image(self, k: int) -> np.ndarray:
        """Press ``k`` against the reference (:func:`display_difference`)."""
        frames, ref = self._linear_frames()
        return display_difference(frames[self._check(k)], ref)
