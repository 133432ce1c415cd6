"""A whole streamed reconstruction in this process: planned, every missing frame run, finished."""

from __future__ import annotations

from pipeline.streaming.files import finish_stream
from pipeline.streaming.frame_setup import prepare
from pipeline.streaming.frames import run_frames
from pipeline.streaming.job import StreamJob
from pipeline.streaming.plan import plan_stream

__all__ = ["reconstruct_stream"]


def reconstruct_stream(capture, *, threads: int | None = 1, progress=None, **options) -> tuple[StreamJob, dict]:
    """Plan, run every missing frame in this process, finish: ``(job, summary)`` (see the module
    docstring; ``options`` as :func:`plan_stream`)."""
    job, cap, lights = plan_stream(capture, **options)
    run = {"frames": 0, "solved": 0, "method": "cached"}
    if not job.cached:
        pipe = prepare(job, cap, lights, threads)
        run = run_frames(job, threads=threads, progress=progress, cap=cap, pipe=pipe)
    summary = finish_stream(job, run) if any(not e["done"] for e in job.entries.values()) else {}
    summary["frames_solved"] = run["solved"]
    summary["method"] = run["method"]
    return job, summary
