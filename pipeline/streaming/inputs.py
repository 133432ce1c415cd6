"""The files a streamed reconstruction reads: the capture (or video) with its frames left on disk, and
the light file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError
from pipeline.streaming.job import LAZY_BYTES

__all__ = ["read_capture", "load_light_record", "colour_matched_record", "job_capture", "job_frames"]


def read_capture(path, video: dict | None = None) -> Any:
    """The ``capture`` record of ``path`` with its large datasets (frames, per-frame truth) left on
    disk (:class:`pipeline.base.store.LazyDataset`); a record in memory is returned as it is.

    A video file (by its suffix) is read as a capture without converting it
    (:func:`pipeline.capture.video_frames.video_capture`; ``video``: its ``reference``,
    ``mm_per_px`` and ``ball_radius_mm``)."""
    from pipeline.base.store import Record, read_record
    from pipeline.capture.video_frames import is_video, video_capture

    if isinstance(path, Record):
        return path
    if is_video(path):
        return video_capture(path, **(video or {}))
    p = Path(path)
    if not p.is_file():
        raise UserError(f"{p}: capture file not found")
    rec = read_record(p, schema="capture", lazy_bytes=LAZY_BYTES)
    for name, value in rec.data.items():  # only the per-frame datasets stay on disk
        if name != "frames" and not name.startswith("truth/") and not isinstance(value, np.ndarray):
            rec.data[name] = np.asarray(value)
    return rec


def load_light_record(path, schema):
    """The light record at ``path`` (a Record as it is; None stays None), or a UserError naming it."""
    from pipeline.base.store import Record, read_record

    if path is None or isinstance(path, Record):
        return path
    if not Path(path).is_file():
        raise UserError(f"{path}: {schema} file not found")
    return read_record(path, schema=schema)


def colour_matched_record(cap, gain):
    """The capture record with its no-contact reference times ``gain (C,)``, rounded and clipped
    to its dtype (:func:`pipeline.capture.shipped.colour_matched`); as it is when ``gain`` is None.
    Its frames stay on disk: the stream matches them a chunk at a time (:func:`pipeline.streaming.frames.run_frames`)."""
    if gain is None or "reference" not in cap.data:
        return cap
    from dataclasses import replace

    from pipeline.capture.shipped import colour_matched

    return replace(cap, data={**cap.data, "reference": colour_matched(np.asarray(cap.data["reference"]), gain)})


def job_capture(job) -> Any:
    """The capture record a worker solves a job's frames with (:func:`read_capture` of its file,
    the reference colour-matched as the plan did)."""
    return colour_matched_record(read_capture(job.capture, job.video), job.options.get("colour_gain"))


def job_frames(job, frames: np.ndarray) -> np.ndarray:
    """Frames as the job solves them: brought to the light model's colours by the plan's gain
    (:func:`pipeline.capture.shipped.colour_matched`) where it matches them, else as read."""
    gain = job.options.get("colour_gain")
    if gain is None:
        return frames
    from pipeline.capture.shipped import colour_matched

    return colour_matched(frames, gain)
