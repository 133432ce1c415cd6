"""A recorded video read as a capture, a chunk of frames at a time, without converting it first.

``iristac batch rec.mp4`` and ``iristac reconstruct rec.mp4`` come here through
:func:`pipeline.streaming.inputs.read_capture`: :func:`video_capture` gives the ``capture`` record of a video
(one white pattern of three colour channels, RGB, as ``iristac import images`` writes a video) whose
``frames`` is a :class:`VideoFrames`, decoded with OpenCV only when a range of them is read.

- **Frames**: decoded sequentially (``cv2.VideoCapture``), BGR turned into RGB exactly once (as
  :func:`calibration.image_import.read_video`). A range before the decoder's position reopens the
  video and decodes forward from its first frame (``grab`` without converting): frame-accurate
  whatever the codec's key frames, and cheap for the increasing ranges the stream reads. The
  whole video is never in memory: one frame at a time is decoded into the caller's buffer.
- **Frame count**: the header's ``CAP_PROP_FRAME_COUNT`` is trusted only once its last frame is
  found there and nothing after it (:func:`video_frame_count`); otherwise the frames are counted by
  decoding to the end once, and a video shorter than its header (a truncated file) is a
  :class:`UserError` naming the file. A frame that still fails to decode while reading is one too.
- **Reference**: ``reference=N`` (default 0, the first frame: a recording that starts before the
  contact) takes frame N as the no-contact reference, and that frame is **not** one of the
  recording's frames (as the image importer leaves its reference out of the presses): result
  frame k is video frame k below N and k + 1 from N on. ``reference="build"`` builds it
  (:func:`calibration.reference.build_reference`) from at most :data:`BUILD_SAMPLE` frames spread
  over the video, and every frame is a recording frame.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError

__all__ = ["VideoFrames", "video_capture", "video_frame_count", "is_video", "parse_reference", "video_options", "BUILD_SAMPLE",
           "DEFAULT_CONTACT_RADIUS"]

#: A built reference is built from at most this many frames, spread evenly over the video.
BUILD_SAMPLE = 64

#: Without a ball radius (a calibration's ``ball_radius_mm``), the contacts masked out while
#: building a reference are taken to be about this fraction of the image's shorter side in radius.
DEFAULT_CONTACT_RADIUS = 0.1


def is_video(path) -> bool:
    """Whether ``path`` names a video file by its suffix (:data:`calibration.image_import.VIDEO_SUFFIXES`)."""
    from calibration.image_import import VIDEO_SUFFIXES

    return isinstance(path, (str, Path)) and Path(path).suffix.lower() in VIDEO_SUFFIXES


def parse_reference(reference) -> int | str:
    """``"build"`` or a frame index (>= 0) from ``--reference`` (None: 0, the first frame).

    >>> parse_reference(None), parse_reference("3"), parse_reference("build")
    (0, 3, 'build')
    """
    if reference is None:
        return 0
    if str(reference) == "build":
        return "build"
    try:
        i = int(reference)
    except (TypeError, ValueError):
        raise UserError(f"--reference {reference!r}: a video's reference is a frame index (0, 1, ...) or 'build'") from None
    if i < 0:
        raise UserError(f"--reference {i}: a frame index is 0 or more")
    return i


def video_options(capture, video: dict | None, cal, ill) -> dict | None:
    """A video file's options for :func:`video_capture` (None for anything else): ``reference``
    (default 0), ``mm_per_px`` (given, else the calibration's or the illumination's attribute) and
    ``ball_radius_mm`` (the calibration's, for a built reference)."""
    if not is_video(capture):
        return None
    v = dict(video or {})
    v["reference"] = parse_reference(v.get("reference"))
    for rec in (cal, ill):
        if v.get("mm_per_px") is None and rec is not None and rec.meta.get("mm_per_px") is not None:
            v["mm_per_px"] = float(rec.meta["mm_per_px"])
    if v.get("ball_radius_mm") is None and cal is not None and cal.meta.get("ball_radius_mm") is not None:
        v["ball_radius_mm"] = float(cal.meta["ball_radius_mm"])
    return v


def _open(path: Path):
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise UserError(f"{path}: not a readable video (OpenCV could not open it)")
    return cap


def video_frame_count(path) -> tuple[int, tuple[int, int]]:
    """``(frames, (H, W))`` of a video, checked (see the module docstring).

    Raises
    ------
    UserError
        Naming the file: unreadable, no frame, not colour, or fewer frames than its header says.
    """
    import cv2

    path = Path(path)
    cap = _open(path)
    try:
        ok, first = cap.read()
        if not ok:
            raise UserError(f"{path}: the video has no frames OpenCV could decode")
        if first.ndim != 3 or first.shape[2] != 3:
            raise UserError(f"{path}: frames of shape {first.shape}; a video recording is read as 3-channel colour")
        shape = (int(first.shape[0]), int(first.shape[1]))
        header = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if header > 0 and cap.set(cv2.CAP_PROP_POS_FRAMES, header - 1) and cap.grab() and not cap.grab():
            return header, shape
    finally:
        cap.release()
    cap = _open(path)  # the header is wrong or unknown: count by decoding once
    try:
        counted = 0
        while cap.grab():
            counted += 1
    finally:
        cap.release()
    if header > 0 and counted < header:
        raise UserError(f"{path}: the video ends after {counted} of the {header} frames its header announces "
                        f"(truncated or damaged file?)")
    return counted, shape


class VideoFrames:
    """A video's frames behind the frame-reader interface of :class:`pipeline.base.h5frames.H5Frames`
    (``shape``, ``dtype``, ``read_into``, a context manager) and as a lazy ``(K, 1, H, W, 3)`` uint8
    array (``frames[a:b]``, ``frames[i]``). ``skip``: the video frame left out (the reference).

    One decoder per object, used by one thread at a time: :meth:`reader` gives a new one over the
    same frames. Picklable (the decoder is reopened where it is used).
    """

    def __init__(self, path, count: int, shape: tuple[int, int], skip: int | None = None):
        self.path = Path(path)
        self.count, self.skip = int(count), skip
        H, W = shape
        self.shape = (self.count - (skip is not None), 1, int(H), int(W), 3)
        self.dtype = np.dtype(np.uint8)
        self._cap: Any = None
        self._next = 0  # the video index the decoder reads next

    def __len__(self) -> int:
        return self.shape[0]

    def reader(self) -> VideoFrames:
        """A new reader (its own decoder) of the same frames."""
        return VideoFrames(self.path, self.count, self.shape[2:4], self.skip)

    def video_index(self, i: int) -> int:
        """The video frame of recording frame ``i``."""
        return i + (self.skip is not None and i >= self.skip)

    def _seek(self, v: int) -> None:
        if self._cap is None or v < self._next:
            self.close()
            self._cap, self._next = _open(self.path), 0
        while self._next < v:
            if not self._cap.grab():
                raise self._ended(self._next)
            self._next += 1

    def _ended(self, v: int) -> UserError:
        return UserError(f"{self.path}: frame {v} of {self.count} could not be decoded (the video ends early or is "
                         f"damaged)")

    def read_video_frame(self, v: int, dst: np.ndarray | None = None) -> np.ndarray:
        """Video frame ``v`` as ``(H, W, 3)`` RGB, into ``dst`` where given."""
        self._seek(v)
        ok, frame = self._cap.read()
        if not ok:
            raise self._ended(v)
        self._next = v + 1
        if frame.shape != tuple(self.shape[2:]):
            raise UserError(f"{self.path}: frame {v} has shape {frame.shape}, the first {tuple(self.shape[2:])}")
        if dst is None:
            dst = np.empty(self.shape[2:], self.dtype)
        dst[...] = frame[..., ::-1]  # BGR -> RGB
        return dst

    def read_into(self, dst: np.ndarray, start: int, stop: int) -> None:
        """Recording frames ``start:stop`` into ``dst (stop - start, 1, H, W, 3)``."""
        for j, i in enumerate(range(start, stop)):
            self.read_video_frame(self.video_index(i), dst[j, 0])

    def __getitem__(self, key) -> np.ndarray:
        if isinstance(key, (int, np.integer)):
            out = np.empty(self.shape[1:], self.dtype)
            self.read_into(out[None], int(key) % len(self), int(key) % len(self) + 1)
            return out
        if isinstance(key, slice) and key.step in (None, 1):
            a, b, _ = key.indices(len(self))
            out = np.empty((max(0, b - a),) + self.shape[1:], self.dtype)
            self.read_into(out, a, max(a, b))
            return out
        raise TypeError(f"VideoFrames: only an index or a contiguous slice, got {key!r}")

    def __array__(self, dtype=None, copy=None):
        raise TypeError(f"{self.path}: a video's frames are read a range at a time, not as one array")

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __enter__(self) -> VideoFrames:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_cap": None, "_next": 0}


def video_capture(path, *, reference=0, mm_per_px: float | None = None, ball_radius_mm: float | None = None):
    """The ``capture`` record of a video (see the module docstring), without reading every frame.

    Parameters
    ----------
    path : path
    reference : int or "build"
        The no-contact frame's index (left out of the frames), or ``"build"``.
    mm_per_px : float
        The pixel pitch (required).
    ball_radius_mm : float, optional
        The contact radius masked out when building a reference (default
        :data:`DEFAULT_CONTACT_RADIUS` of the shorter image side).

    Returns
    -------
    Record
        ``frames`` (:class:`VideoFrames`, ``(K, 1, H, W, 3)`` uint8), ``reference (1, H, W, 3)``,
        ``drive (1, 3, 3)``, ``brightness (1,)``; attributes ``source: video``, ``mm_per_px``,
        ``video_reference`` (``"N"`` or ``"build:<sample>"``: part of the capture's key), ...
    """
    from pipeline.base.store import Record

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: video file not found")
    if mm_per_px is None or not (np.isfinite(mm_per_px) and mm_per_px > 0):
        raise UserError(f"{path}: a video needs the pixel pitch: give --mm-per-px, or a calibration or illumination "
                        f"with a mm_per_px attribute (got {mm_per_px})")
    reference = parse_reference(reference)
    count, shape = video_frame_count(path)
    meta: dict[str, Any] = {"source": "video", "original_file": path.name, "mode": "trichromatic", "bit_depth": 8,
                            "pattern_names": ["white"], "mm_per_px": float(mm_per_px), "video_frames": count}
    if reference == "build":
        ref, note = _built(path, count, shape, mm_per_px, ball_radius_mm)
        frames = VideoFrames(path, count, shape)
        meta.update(reference_name="built", reference_source=note, video_reference=f"build:{BUILD_SAMPLE}")
    else:
        if not reference < count or count < 2:
            raise UserError(f"{path}: --reference {reference} is not a frame of this video's {count} (and a recording "
                            f"needs a frame besides its reference)")
        frames = VideoFrames(path, count, shape, skip=int(reference))
        with frames.reader() as r:
            ref = r.read_video_frame(int(reference))[None]
        meta.update(reference_name=str(reference), reference_source=f"frame {reference}",
                    video_reference=str(reference))
    data = {"frames": frames, "reference": np.ascontiguousarray(ref),
            "drive": np.eye(3, dtype=np.float32)[None], "brightness": np.ones(1, np.float32)}
    return Record(schema="capture", data=data, meta=meta, path=path)  # type: ignore[arg-type]


def _built(path: Path, count: int, shape, mm_per_px: float, ball_radius_mm: float | None) -> tuple[np.ndarray, str]:
    """The reference ``(1, H, W, 3)`` uint8 built from a sample of the video's frames, and its note."""
    from calibration.reference import build_reference

    if count < 3:
        raise UserError(f"{path}: --reference build needs at least 3 frames, the video has {count}")
    sample = np.unique(np.linspace(0, count - 1, min(BUILD_SAMPLE, count)).round().astype(int))
    frames = VideoFrames(path, count, shape)
    stack = np.empty((len(sample), 1) + tuple(shape) + (3,), np.uint8)
    with frames:
        for j, v in enumerate(sample):
            frames.read_video_frame(int(v), stack[j, 0])
    radius_px = (ball_radius_mm / mm_per_px) if ball_radius_mm else DEFAULT_CONTACT_RADIUS * min(shape)
    ref, report = build_reference(stack.astype(np.float32), float(radius_px))
    ref = np.clip(np.round(ref), 0, 255).astype(np.uint8)
    return ref, f"{report['note']} (a sample of {len(sample)} of the video's {count} frames)"
