"""The files a streamed reconstruction reads: the capture (or video) with its frames left on disk, and
the light file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError
from pipeline.streaming.job import LAZY_BYTES

__all__ = ["read_capture", "load_light_record"]


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
