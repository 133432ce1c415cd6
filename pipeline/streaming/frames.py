"""The frames of a streamed reconstruction: read a chunk ahead, solved, written a chunk behind."""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numpy as np

from pipeline.frame_pipeline.outputs import OutputSpec
from pipeline.streaming.files import open_ranges
from pipeline.streaming.job import StreamJob
from pipeline.streaming.writer import ChunkWriter

__all__ = ["run_frames", "frame_stats", "ArrayFrames"]


def run_frames(job: StreamJob, start: int | None = None, stop: int | None = None, *, cap, pipe,
               threads: int | None = 1, progress: Callable[[int], None] | None = None, keep: bool = False) -> dict:
    """Write the frames ``start:stop`` (default: every frame no progress file claims) of the job's
    unfinished entries; returns ``{"frames": written, "solved": frames solved (0 where the normals
    and heights were read back), "seconds", "method", "worker"}``.

    ``cap`` is the job's capture record (:func:`pipeline.streaming.inputs.read_capture`) and
    ``pipe`` its frame pipeline (:func:`pipeline.streaming.frame_setup.prepare`); a worker
    process or a Dask worker builds both once and calls this with each of its frame ranges.
    ``progress(n)`` is called after every chunk with its frames. ``keep``: the pipeline stays open
    for the caller's next range (else it is closed here).
    """
    import socket

    from pipeline.base.threads import limit_threads

    t0 = time.perf_counter()
    truth, stored = _Truth(cap, job.region), _Stored(job)
    source = _frame_source(job, cap, pipe)
    files, ranges = open_ranges(job, start, stop)
    written = 0
    try:
        # One BLAS thread per caller (the frame pipeline's threads are the parallelism; OpenBLAS
        # workers on top would fight them for the cores), as live does.
        with limit_threads(blas=1), source as reader, ChunkWriter(files) as writer:
            for a, b in ranges:
                writer.begin(a, b)
                written += _run_range(job, pipe, reader, writer, truth, stored, a, b, progress)
                writer.end()
    finally:
        if not keep:
            pipe.close()
    solved = written if not (job.entries["normals"]["done"] and job.entries["depth"]["done"]) else 0
    return {"frames": written, "solved": solved, "seconds": time.perf_counter() - t0,
            "method": pipe.method if solved else "cached", "worker": f"{socket.gethostname()}:{os.getpid()}"}


def _frame_source(job: StreamJob, cap, pipe) -> Any:
    """The reader of the capture's frames: in memory, a video's own decoder, or the capture file's
    frames decoded on threads (a device's pipeline leaves the CPU's cores to decoding them)."""
    from pipeline.base.h5frames import H5Frames
    from pipeline.capture.video_frames import VideoFrames

    frames = cap.data["frames"]
    if isinstance(frames, np.ndarray):
        return ArrayFrames(frames)
    if isinstance(frames, VideoFrames):
        return frames.reader()  # a decoder of its own
    readers = (os.cpu_count() or 2) if pipe.method.startswith("device") else max(2, pipe.threads)
    return H5Frames(job.capture, "frames", threads=readers)


def _run_range(job: StreamJob, pipe, reader, writer, truth, stored, a: int, b: int, progress) -> int:
    """Frames ``a:b`` chunk by chunk, the next chunk read while this one is solved."""
    from pipeline.streaming.inputs import job_frames

    shape = (job.chunk,) + tuple(reader.shape[1:])
    bufs = [np.empty(shape, reader.dtype), np.empty(shape, reader.dtype)]
    starts = list(range(a, b, job.chunk))
    with ThreadPoolExecutor(1, thread_name_prefix="iristac-read") as pool:
        def read(i):
            s = starts[i]
            n = min(job.chunk, b - s)
            reader.read_into(bufs[i % 2][:n], s, s + n)
            return bufs[i % 2][:n]

        nxt = pool.submit(read, 0) if starts else None
        for i, s in enumerate(starts):
            chunk = nxt.result()
            # The next chunk goes into the previous chunk's buffer: its solve is done (the writer
            # gets results, never frames).
            nxt = pool.submit(read, i + 1) if i + 1 < len(starts) else None
            out = pipe.run(job_frames(job, chunk), *stored.read(s, s + len(chunk)))
            arrays = _arrays(out, job.outputs)
            writer.write(s, arrays, frame_stats(out, arrays, truth, s))
            if progress is not None:
                progress(len(out))
    return b - a


class ArrayFrames:
    """Frames already in memory (a capture record that was never a file) behind the reader
    interface of :class:`pipeline.base.h5frames.H5Frames`."""

    def __init__(self, frames: np.ndarray):
        self.frames = frames
        self.shape, self.dtype = frames.shape, frames.dtype

    def read_into(self, dst: np.ndarray, start: int, stop: int) -> None:
        dst[...] = self.frames[start:stop]

    def __enter__(self) -> ArrayFrames:
        return self

    def __exit__(self, *exc) -> None:
        pass


class _Stored:
    """The normals and heights a finished entry already holds (results of another command), read a
    chunk at a time so the frames are not solved again; None where they are to be computed."""

    def __init__(self, job: StreamJob):
        from pipeline.base.store import read_record

        self.normals = self.depth = None
        e = job.entries
        if e["normals"]["done"]:
            self.normals = read_record(e["normals"]["path"], "normals", lazy_bytes=0).data
            if e["depth"]["done"]:
                self.depth = read_record(e["depth"]["path"], "depth", lazy_bytes=0).data

    def read(self, a: int, b: int) -> tuple:
        n = None if self.normals is None else (self.normals["normals"][a:b], self.normals["mask"][a:b])
        d = None if self.depth is None else (self.depth["height"][a:b], self.depth["mask"][a:b])
        return n, d


def _arrays(out, outputs: OutputSpec) -> dict:
    """The chunk's datasets per entry, in the written dtypes (the pipeline's arrays are new each
    chunk but for the fast near-field path's extras, views of planes it reuses: copied)."""
    dt = outputs.normals_dtype
    n = {"normals": out.normals.astype(dt, copy=False), "mask": out.mask}
    if out.confidence is not None:
        n["confidence"] = out.confidence.astype(dt, copy=False)
    for name in outputs.normal_extras:
        n[name] = np.array(out.extras[name], np.int32 if name == "count" else np.float32, order="C")
    arrays = {"normals": n, "depth": {"height": out.height, "mask": out.height_mask}}
    if out.contact is not None:
        arrays["contact"] = {"contact": out.contact}
    return arrays


def frame_stats(out, arrays: dict, truth, start: int) -> dict[int, dict]:
    """Per frame: valid pixels, drift facts, contact pixels and errors against truth (what
    :meth:`pipeline.streaming.job.StreamJob.summarize` sums up; the checksums are the writer's)."""
    stats = {}
    errs = truth.errors(out, start)
    for k in range(len(out)):
        st = {"valid": int(out.mask[k].sum())}
        st.update({m: out.meta[k][m] for m in ("drift", "drift_before_dn", "drift_residual_dn") if m in out.meta[k]})
        if out.contact is not None:
            st["contact"] = int(out.contact[k].sum())
        st.update(errs[k])
        stats[start + k] = st
    return stats


class _Truth:
    """Errors against a capture's truth, a chunk at a time (:func:`pipeline.results.evaluate.truth_errors`'
    per-frame parts)."""

    def __init__(self, cap, region):
        self.normals = cap.data.get("truth/normals")
        self.height = cap.data.get("truth/height")
        self.region = None if region is None else np.asarray(region, bool)

    def errors(self, out, start: int) -> list[dict]:
        from pipeline.results.evaluate import mean_angular_error_deg

        n = len(out)
        res: list[dict] = [{} for _ in range(n)]
        if self.normals is not None:
            gt = np.asarray(self.normals[start:start + n])
            for k in range(n):
                m = np.einsum("hwc,hwc->hw", gt[k], gt[k]) > 0
                if self.region is not None:
                    m &= self.region
                res[k]["normal_error_deg"] = mean_angular_error_deg(out.normals[k], gt[k], m)
        if self.height is not None:
            gt = np.asarray(self.height[start:start + n])
            for k in range(n):
                diff = out.height[k].astype(np.float64) - gt[k]
                if self.region is not None:
                    diff = diff[self.region]
                res[k]["depth_sq_mm2"] = float(np.sum(diff ** 2))
                res[k]["depth_px"] = int(diff.size)
        return res
