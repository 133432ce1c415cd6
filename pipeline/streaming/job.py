"""What a streamed reconstruction decides before its first frame: :class:`StreamJob`, and the sizes
that bound its memory and its losses."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.frame_pipeline.outputs import OutputSpec
from pipeline.stages.base import StageSpec

__all__ = ["StreamJob", "CONTACT_SPEC", "CHUNK_BYTES", "DEVICE_CHUNK", "VERIFY_BYTES", "LAZY_BYTES"]

#: The contact mask's entry: keyed on the depth entry and the capture (the colour change is the
#: capture's, the height the depth's).
CONTACT_SPEC = StageSpec("contact", version=1, schema="contact")

#: A chunk's frames and results take about this many bytes (at least two frames a thread, at most
#: 256 frames): 24 frames of 320 x 240, whose results are about 8 times their 8-bit frames.
CHUNK_BYTES = 48 << 20

#: Frames a chunk holds at least on a GPU (one upload, one launch per chunk).
DEVICE_CHUNK = 512

#: Finished entries up to this size are read whole to be checked before they are trusted.
VERIFY_BYTES = 256 << 20

#: A capture's datasets above this many bytes stay on disk until a chunk of them is read.
LAZY_BYTES = 8 << 20


@dataclass
class StreamJob:
    """Everything decided before the first frame (picklable: a worker process or a Dask worker
    rebuilds its solver from it, :func:`pipeline.streaming.frames.run_frames`).

    Attributes
    ----------
    capture : str
        The capture file (or video file).
    light_files : dict
        ``calibration`` / ``illumination`` path (or None: the capture's own lights).
    options : dict
        ``solver``, ``integrator``, ``ratio``, ``max_condition``, ``device``, ``dtype``,
        ``compile``, ``drift``.
    outputs : OutputSpec
    region, markers : (H, W) bool or None
        The solved pixels (a user's mask); the printed markers filled in.
    entries : dict
        ``normals`` / ``depth`` / ``contact`` -> ``{"key": StageKey, "path": str, "done": bool}``.
    frames : int
    shape : (H, W)
    mm_per_px : float
    video : dict or None
        A video's ``reference``, ``mm_per_px``, ``ball_radius_mm`` (:func:`pipeline.streaming.inputs.read_capture`); None for a capture file.
    """

    capture: str
    light_files: dict
    options: dict
    outputs: OutputSpec
    region: np.ndarray | None
    markers: np.ndarray | None
    entries: dict
    frames: int
    shape: tuple[int, int]
    mm_per_px: float
    user_region: bool = False
    chunk: int = 64
    meta: dict = field(default_factory=dict)
    video: dict | None = None

    @property
    def cached(self) -> bool:
        return all(e["done"] for e in self.entries.values())

    @property
    def filled(self) -> np.ndarray | None:
        """The marker pixels filled in and solved: the markers within the solved region (None: no markers)."""
        return None if self.markers is None else self.markers & (self.region if self.region is not None else True)

    def summarize(self, stats: dict[int, dict]) -> dict:
        """The run's summary from its frames' statistics (:func:`pipeline.streaming.frames.frame_stats`):
        ``valid_fraction``, ``drift`` (and its median DN before and after), the truth errors
        (``normal_mean_error_deg``, ``depth_rmse_mm``) and ``contact_fraction``, each where every
        frame has it."""
        out: dict[str, Any] = {}
        H, W = self.shape
        if not stats:
            return out
        frames = [stats[k] for k in sorted(stats)]
        out["valid_fraction"] = float(sum(s["valid"] for s in frames) / (len(frames) * H * W))
        if all("drift_before_dn" in s for s in frames):
            out["drift"] = str(frames[0].get("drift", "none"))
            out["drift_before_dn"] = float(np.median([s["drift_before_dn"] for s in frames]))
            out["drift_residual_dn"] = float(np.median([s["drift_residual_dn"] for s in frames]))
        else:
            out["drift"] = "none"
        if all("normal_error_deg" in s for s in frames):
            out["normal_mean_error_deg"] = float(np.mean([s["normal_error_deg"] for s in frames]))
        if all("depth_sq_mm2" in s for s in frames):
            out["depth_rmse_mm"] = float(np.sqrt(sum(s["depth_sq_mm2"] for s in frames) /
                                                 max(1, sum(s["depth_px"] for s in frames))))
        if all("contact" in s for s in frames):
            out["contact_fraction"] = float(sum(s["contact"] for s in frames) / (len(frames) * H * W))
        return out
