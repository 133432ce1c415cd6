"""A capture or recording reconstructed as a stream of frame chunks, straight into the store.

``iristac reconstruct`` and ``iristac batch`` both come here. A recording of any length is read,
solved, integrated and written a chunk of frames at a time, so memory does not grow with it:

1. **plan** (:func:`plan_stream`): the capture is opened without reading its frames (its
   large datasets stay on disk, :class:`pipeline.base.store.LazyDataset`), the light model
   loaded, and the keys of the results computed as the stages compute them
   (:func:`pipeline.stages.normals.key_params`, :mod:`pipeline.stages.depth`; the contact mask's
   entry on the depth entry and the capture): the same work through ``run``, ``reconstruct`` or
   ``batch`` is one cache entry. A complete entry is read back, not recomputed.
2. **frames** (:func:`run_frames`): what is missing is written into partial store files
   (:class:`pipeline.base.streamed.StreamedFile`) a chunk at a time by the one frame pipeline
   (:class:`pipeline.frame_pipeline.FramePipeline`: the solver's fast path where it has one,
   frames in parallel on ``threads`` threads), while the next chunk is read
   (:class:`pipeline.base.h5frames.H5Frames`) and the last one written and made durable on
   other threads. A killed run resumes from the last chunk its progress files record; a
   worker process or a Dask worker runs the same function on its own frame range.
3. **finish** (:func:`finish_stream`): the summaries (valid fraction, drift, errors against
   truth where the capture has it) go into the files' attributes, the files are renamed into
   place.

``--out`` folders get hard links to the store's files (symbolic links across file systems),
never a second copy (:func:`link_outputs`).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.base.errors import UserError
from pipeline.frame_pipeline.outputs import OutputSpec
from pipeline.stages.base import StageSpec

__all__ = ["StreamJob", "load_light_record", "plan_stream", "prepare", "open_files", "run_frames", "finish_stream", "reconstruct_stream", "link_outputs",
           "CONTACT_SPEC", "read_capture", "video_options", "CHUNK_BYTES", "COMMIT_SECONDS"]

#: The contact mask's entry: keyed on the depth entry and the capture (the colour change is the
#: capture's, the height the depth's).
CONTACT_SPEC = StageSpec("contact", version=1, schema="contact")

#: A chunk's frames and results take about this many bytes (at least two frames a thread, at most
#: 256 frames): 24 frames of 320 x 240, whose results are about 8 times their 8-bit frames.
CHUNK_BYTES = 48 << 20

#: What is written is made durable (fsync) and recorded as done about this often (a kill loses at
#: most this much work; fsync more often cost the solving threads CPU time on a 2-core machine).
COMMIT_SECONDS = 2.0

#: Frames a chunk holds at least on a GPU (one upload, one launch per chunk).
DEVICE_CHUNK = 512

#: Finished entries up to this size are read whole to be checked before they are trusted.
VERIFY_BYTES = 256 << 20

#: A capture's datasets above this many bytes stay on disk until a chunk of them is read.
LAZY_BYTES = 8 << 20


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


@dataclass
class StreamJob:
    """Everything decided before the first frame (picklable: a worker process or a Dask worker
    rebuilds its solver from it, :func:`run_frames`).

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
        A video's ``reference``, ``mm_per_px``, ``ball_radius_mm`` (:func:`read_capture`); None for a capture file.
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


def load_light_record(path, schema):
    """The light record at ``path`` (a Record as it is; None stays None), or a UserError naming it."""
    from pipeline.base.store import Record, read_record

    if path is None or isinstance(path, Record):
        return path
    if not Path(path).is_file():
        raise UserError(f"{path}: {schema} file not found")
    return read_record(path, schema=schema)


def plan_stream(capture, *, calibration=None, illumination=None, solver: str = "lstsq", integrator: str = "dst",
                store=None, ratio: bool = False, max_condition: float = 1e3, device="cpu", dtype="float32",
                compile: bool = False, mask=None, markers=None, drift: str = "auto", outputs: OutputSpec | None = None,
                force: bool = False, heal: bool = True, video: dict | None = None) -> tuple[StreamJob, Any, Any]:
    """``(job, capture record, lights)``: the keys of the results, and which of them the store has
    (see the module docstring; arguments as :func:`pipeline.reconstruct.reconstruct`; ``video``:
    ``reference`` and ``mm_per_px`` of a video file, :func:`video_options`)."""
    from pipeline.base.registry import INTEGRATORS, SOLVERS
    from pipeline.base.store import StageStore
    from pipeline.stages import capture as capture_stage
    from pipeline.stages import depth as depth_stage
    from pipeline.stages import normals as normals_stage

    SOLVERS.check(solver)
    INTEGRATORS.check(integrator)
    outputs = outputs or OutputSpec()
    cal = load_light_record(calibration, "calibration")
    ill = load_light_record(illumination, "illumination")
    video = video_options(capture, video, cal, ill)
    cap = read_capture(capture, video)
    lights = normals_stage.capture_lights(cap, cal, ill)
    from pipeline.normals.lights import check_lights

    check_lights(solver, lights, cap.data["frames"].shape[1], cap.data["frames"].shape[-1])
    if ratio and normals_stage.reference_frames(cap) is None:
        raise UserError(f"{cap.path}: --ratio needs no-contact reference frames (dataset 'reference'); this "
                        f"capture has none (source {cap.meta.get('source')!r})")
    region = normals_stage.capture_region(cap, mask)
    marks = normals_stage.marker_mask(cap, markers, lights)
    user_region = None if mask is None else region
    store = store if isinstance(store, StageStore) else StageStore(store)
    cap_key = capture_stage.capture_key(store, cap)
    n_key = normals_stage.SPEC.key(store, normals_stage.key_params(
        lights, solver=solver, ratio=ratio, max_condition=max_condition, dtype=dtype, mask=user_region,
        markers=marks, drift=drift, outputs=outputs), [cap_key, lights.key])
    mm = float(cap.meta["mm_per_px"])
    d_key = depth_stage.SPEC.key(store, depth_stage.params({"integrator": integrator, "mm_per_px": mm}), [n_key])
    keys = {"normals": n_key, "depth": d_key}
    if outputs.contact:
        keys["contact"] = CONTACT_SPEC.key(store, {}, [d_key, cap_key])
    entries = {}
    for name, key in keys.items():
        # Entries up to VERIFY_BYTES are read whole (their checksums verified, a bad one healed);
        # larger ones (a long recording's, written unfiltered) by their structure.
        path = store.path_for(key)
        load = path.is_file() and path.stat().st_size <= VERIFY_BYTES
        done = not force and store.get(key, recompute_bad=heal, load=load) is not None
        entries[name] = {"key": key, "path": str(store.path_for(key)), "done": done}
    K, P, H, W, C = cap.data["frames"].shape
    frame_bytes = P * H * W * C * np.dtype(cap.data["frames"].dtype).itemsize + 32 * H * W  # frames, results
    job = StreamJob(capture=str(Path(cap.path).resolve()) if cap.path else "",
                    light_files={"calibration": None if cal is None else str(cal.path),
                                 "illumination": None if ill is None else str(ill.path)},
                    options={"solver": solver, "integrator": integrator, "ratio": bool(ratio),
                             "max_condition": float(max_condition), "device": str(device), "dtype": str(dtype),
                             "compile": bool(compile), "drift": drift},
                    outputs=outputs, region=region, markers=marks, entries=entries, frames=int(K), shape=(H, W),
                    mm_per_px=mm, user_region=mask is not None,
                    chunk=int(min(256, max(4, CHUNK_BYTES // frame_bytes))), video=video)
    return job, cap, lights


def video_options(capture, video: dict | None, cal, ill) -> dict | None:
    """A video file's options for :func:`read_capture` (None for anything else): ``reference``
    (default 0), ``mm_per_px`` (given, else the calibration's or the illumination's attribute) and
    ``ball_radius_mm`` (the calibration's, for a built reference)."""
    from pipeline.capture.video_frames import is_video, parse_reference

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


# ----------------------------------------------------------------------------------------------
# The frames
# ----------------------------------------------------------------------------------------------

def _pipeline(job: StreamJob, cap, lights, threads):
    """The :class:`~pipeline.frame_pipeline.FramePipeline` of ``job`` on ``threads`` threads."""
    from pipeline.depth import frame_integrator
    from pipeline.frame_pipeline import FramePipeline
    from pipeline.normals.drift import STREAM_SAMPLES
    from pipeline.stages.fast_solvers import frame_solver
    from pipeline.stages.normals import reference_frames

    o = job.options
    frames = cap.data["frames"]
    H, W = job.shape
    if _on_device(job, lights, frames):
        from pipeline.frame_pipeline.device import DeviceFramePipeline
        from pipeline.frame_pipeline.gpu_stream import GPUFramePipeline

        cuda = str(o["device"]).startswith("cuda")
        return DeviceFramePipeline(GPUFramePipeline(
            lights.field, job.mm_per_px, dark=cap.data.get("dark"), flat_field=lights.flat_field,
            max_condition=o["max_condition"], solver="fused" if cuda else "torch", device=o["device"], host_threads=1))
    solver = frame_solver(o["solver"], lights, shape=(H, W), channels=frames.shape[-1],
                          reference=reference_frames(cap), dark=cap.data.get("dark"), markers=job.markers,
                          max_condition=o["max_condition"], region=job.region, drift=o["drift"],
                          drift_samples=STREAM_SAMPLES, drift_every=1, raw_dtype=frames.dtype,
                          bit_depth=cap.meta.get("bit_depth"), name=str(cap.path or "capture"), ratio=o["ratio"],
                          device=o["device"], dtype=o["dtype"], compile=o["compile"])
    integ = frame_integrator(o["integrator"], (H, W), job.mm_per_px)
    contact = _contact_fn(job, cap, lights) if job.outputs.contact and not job.entries["contact"]["done"] else None
    filled = None if job.markers is None else job.markers & (job.region if job.region is not None else True)
    return FramePipeline(solver, integ, threads=threads, region=job.region, filled=filled, contact=contact,
                         extras=job.outputs.normal_extras + (() if "groups" in job.meta else ("albedo",)))


def _on_device(job: StreamJob, lights, frames) -> bool:
    """Whether the job runs the fused device pipeline: ``nearfield`` and ``dst`` on the whole frame of
    integer frames on a device other than the CPU, with nothing the device pipeline does not do
    (a region, markers, a ratio, a drift, float64, the contact mask)."""
    o = job.options
    return (str(o["device"]) != "cpu" and o["solver"] == "nearfield" and o["integrator"] == "dst"
            and job.region is None and job.markers is None and not o["ratio"] and o["dtype"] == "float32"
            and o["drift"] in ("auto", "none") and lights.field is not None and np.dtype(frames.dtype).kind in "ui"
            and not (job.outputs.contact and not job.entries.get("contact", {}).get("done", True))
            and not job.outputs.normal_extras)


def _contact_fn(job: StreamJob, cap, lights):
    """``contact(frames, height, valid)`` of one frame set (:func:`pipeline.contact.contact_mask`),
    against the capture's reference, else the one the solver's model stores, else the height alone."""
    from pipeline.contact import contact_mask, contact_reference_level, drift_estimator
    from pipeline.normals.solve import stored_reference
    from pipeline.stages.normals import reference_frames

    ref = reference_frames(cap)
    if ref is None:
        ref = stored_reference(lights, job.options["solver"])
    frames = cap.data["frames"]
    if ref is None or np.shape(ref) != tuple(frames.shape[1:]):
        def height_only(f, h, v):
            return contact_mask(height=h, valid=v) & (True if job.region is None else job.region)

        return height_only
    ref = np.asarray(ref)
    est, level = drift_estimator(ref), contact_reference_level(ref)

    def touch(f, h, v):
        m = contact_mask(f, ref, h, valid=v, estimator=est, reference_level=level)
        return m if job.region is None else m & job.region

    return touch


def prepare(job: StreamJob, cap, lights, threads: int | None = 1):
    """The job's frame pipeline, and what its files' layout needs to know from a first solve (the
    albedo groups, whether the solver rates its normals): one frame solved once, set in
    ``job.meta``. Returns the pipeline."""
    pipe = _pipeline(job, cap, lights, threads)
    if pipe.method.startswith("device"):
        job.chunk = max(job.chunk, DEVICE_CHUNK)
    if "groups" not in job.meta and job.frames and not job.entries["normals"]["done"]:
        probe = pipe.run(np.asarray(cap.data["frames"][0:1]))
        job.meta["groups"] = int(probe.extras["albedo"].shape[-1]) if "albedo" in probe.extras else 1
        job.meta["confidence"] = probe.confidence is not None
        # What the solver says of itself (its method, what its confidence measures): the record's.
        skip = ("drift", "drift_before_dn", "drift_residual_dn", "solver", "max_condition", "ratio")
        job.meta["solver_meta"] = {k: v for k, v in probe.meta[0].items() if k not in skip}
    pipe.extras = job.outputs.normal_extras  # the probe's albedo was only to learn its groups
    job.meta.setdefault("lights", lights.source)
    return pipe


def open_files(job: StreamJob) -> dict:
    """The partial files of the entries still to write: created, or opened to resume
    (:class:`pipeline.base.streamed.StreamedFile`)."""
    from pipeline.base.streamed import StreamedFile

    H, W = job.shape
    meta_n = {**job.meta.get("solver_meta", {}), "solver": job.options["solver"], "mm_per_px": job.mm_per_px,
              "ratio": job.options["ratio"], "max_condition": job.options["max_condition"],
              "lights": job.meta.get("lights", "")}
    layouts = {"normals": ("normals", job.outputs.normals_datasets((H, W), job.meta.get("groups", 1),
                                                                   job.meta.get("confidence", False)), meta_n),
               "depth": ("depth", OutputSpec.depth_datasets((H, W)),
                         {"integrator": job.options["integrator"], "mm_per_px": job.mm_per_px}),
               "contact": ("contact", OutputSpec.contact_datasets((H, W)), {})}
    out = {}
    for name, e in job.entries.items():
        if e["done"]:
            continue
        schema, datasets, meta = layouts[name]
        static = {}
        if name == "normals" and job.markers is not None:
            static["filled"] = job.markers & (job.region if job.region is not None else True)
        out[name] = StreamedFile.open(e["path"], schema, job.frames, datasets, static=static, meta=meta, key=e["key"])
    return out


def run_frames(job: StreamJob, start: int | None = None, stop: int | None = None, *, threads: int | None = 1,
               progress: Callable[[int], None] | None = None, cap=None, lights=None, pipe=None,
               keep: bool = False) -> dict:
    """Write the frames ``start:stop`` (default: every frame no progress file claims) of the job's
    unfinished entries; returns ``{"frames": written, "solved": frames solved (0 where the normals
    and heights were read back), "seconds", "method", "worker"}``.

    A worker process or a Dask worker calls it with its frame range (``cap`` and ``lights`` None:
    read again from the job's files). ``progress(n)`` is called after every chunk with its frames.
    ``keep``: the pipeline stays open for the caller's next range (else it is closed here).
    """
    from pipeline.base.h5frames import H5Frames
    from pipeline.base.threads import limit_threads
    from pipeline.capture.video_frames import VideoFrames

    t0 = time.perf_counter()
    if cap is None:
        cap = read_capture(job.capture, job.video)
    if lights is None:
        from pipeline.stages.normals import capture_lights

        lights = capture_lights(cap, load_light_record(job.light_files["calibration"], "calibration"),
                                load_light_record(job.light_files["illumination"], "illumination"))
    if pipe is None:
        pipe = prepare(job, cap, lights, threads)
    files = open_files(job)
    ranges = _ranges(files, start, stop)
    written = 0
    # One BLAS thread per caller (the frame pipeline's threads are the parallelism; OpenBLAS
    # workers on top would fight them for the cores), as live does.
    frames = cap.data["frames"]
    # A device's pipeline leaves the CPU's cores to decoding the frames.
    readers = (os.cpu_count() or 2) if pipe.method.startswith("device") else max(2, pipe.threads)
    source: Any
    if isinstance(frames, np.ndarray):
        source = ArrayFrames(frames)
    elif isinstance(frames, VideoFrames):
        source = frames.reader()  # a decoder of its own
    else:
        source = H5Frames(job.capture, "frames", threads=readers)
    try:
        with limit_threads(blas=1), source as reader, _Writer(files) as writer:
            truth, stored = _Truth(cap, job.region), _Stored(job)
            for a, b in ranges:
                writer.begin(a, b)
                written += _run_range(job, pipe, reader, writer, truth, stored, a, b, progress)
                writer.end()
    finally:
        if not keep:
            pipe.close()
    import socket

    solved = written if not (job.entries["normals"]["done"] and job.entries["depth"]["done"]) else 0
    return {"frames": written, "solved": solved, "seconds": time.perf_counter() - t0,
            "method": pipe.method if solved else "cached", "worker": f"{socket.gethostname()}:{os.getpid()}"}


def _ranges(files: dict, start, stop) -> list[tuple[int, int]]:
    """The frame ranges to write: what any unfinished file misses, within ``start:stop``."""
    from pipeline.base.streamed import merge_ranges

    missing = merge_ranges(r for sf in files.values() for r in sf.missing())
    lo = 0 if start is None else int(start)
    hi = max((sf.frames for sf in files.values()), default=0) if stop is None else int(stop)
    return [(max(a, lo), min(b, hi)) for a, b in missing if min(b, hi) > max(a, lo)]


def _run_range(job: StreamJob, pipe, reader, writer, truth, stored, a: int, b: int, progress) -> int:
    """Frames ``a:b`` chunk by chunk, the next chunk read while this one is solved."""
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
            out = pipe.run(chunk, *stored.read(s, s + len(chunk)))
            arrays = _arrays(out, job.outputs)
            writer.write(s, arrays, _frame_stats(out, arrays, truth, s))
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


def _frame_stats(out, arrays: dict, truth, start: int) -> dict[int, dict]:
    """Per frame: valid pixels, drift facts, contact pixels, errors against truth, and checksums
    of the normals and heights written (the entries' content digests: :func:`_digest`)."""
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
    """Errors against a capture's truth, a chunk at a time (:func:`pipeline.evaluate.truth_errors`'
    per-frame parts)."""

    def __init__(self, cap, region):
        self.normals = cap.data.get("truth/normals")
        self.height = cap.data.get("truth/height")
        self.region = None if region is None else np.asarray(region, bool)

    def errors(self, out, start: int) -> list[dict]:
        from pipeline.evaluate import mean_angular_error_deg

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


class _Writer:
    """Writes chunks on a thread of its own; on another, at most every :data:`COMMIT_SECONDS` (and at
    the end of a range), makes what is written durable (fsync) and records it, so the solving
    never waits for the disk to catch up, only for the page cache to take a chunk."""

    def __init__(self, files: dict):
        self.files = files
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="iristac-write")
        self.syncer = ThreadPoolExecutor(1, thread_name_prefix="iristac-sync")
        self.pending = self.syncing = None
        self.writers: dict = {}
        self.stats: dict[int, dict] = {}
        self.done = 0
        self.last_commit = time.monotonic()

    def begin(self, a: int, b: int) -> None:
        self.writers = {name: sf.writer(a, b) for name, sf in self.files.items()}
        self.stats, self.done = {}, a

    def write(self, at: int, arrays: dict, stats: dict) -> None:
        self._wait()  # one chunk in flight: memory stays one chunk's
        self.pending = self.pool.submit(self._write, at, arrays, stats)

    def _write(self, at: int, arrays: dict, stats: dict) -> None:
        for name, w in self.writers.items():
            w.write(at, arrays[name])
        self.stats.update(stats)
        self.done = at + len(next(iter(arrays["depth"].values())))
        if time.monotonic() - self.last_commit >= COMMIT_SECONDS and (self.syncing is None or self.syncing.done()):
            if self.syncing is not None:
                self.syncing.result()  # raise what the last commit raised
            done, st, self.stats = self.done, self.stats, {}
            self.last_commit = time.monotonic()
            self.syncing = self.syncer.submit(self._commit, done, st)

    def _commit(self, done: int, stats: dict) -> None:
        for w in self.writers.values():
            w.commit(done, stats)

    def _wait(self) -> None:
        if self.pending is not None:
            p, self.pending = self.pending, None
            p.result()

    def _wait_sync(self) -> None:
        if self.syncing is not None:
            s, self.syncing = self.syncing, None
            s.result()

    def end(self) -> None:
        self._wait()
        self._wait_sync()
        self._commit(self.done, self.stats)
        self.stats = {}
        for w in self.writers.values():
            w.close()
        self.writers = {}

    def __enter__(self) -> _Writer:
        return self

    def __exit__(self, *exc) -> None:
        try:
            self._wait()
            self._wait_sync()
        finally:
            for w in self.writers.values():
                w.close()
            self.pool.shutdown()
            self.syncer.shutdown()


# ----------------------------------------------------------------------------------------------
# Finishing
# ----------------------------------------------------------------------------------------------

def finish_stream(job: StreamJob, files_meta: dict | None = None) -> dict:
    """Summaries into the unfinished entries' attributes, the entries renamed into place. Returns
    the summary (``valid_fraction``, ``drift``, truth errors, ``contact_fraction``)."""
    summary: dict[str, Any] = {}
    stats: dict[int, dict] = {}
    todo = {}
    for name, e in job.entries.items():  # finished meanwhile by another job of the same work
        if not e["done"] and Path(e["path"]).is_file() and not _partial_exists(e["path"]):
            e["done"] = True
    for name, sf in open_files(job).items():
        todo[name] = sf
        for k, v in sf.stats().items():
            stats.setdefault(k, {}).update(v)
    if todo and len(stats) < job.frames:
        raise UserError(f"{job.capture}: {job.frames - len(stats)} of {job.frames} frames have no results yet")
    summary.update(_summary(job, stats))
    meta_n = {"valid_fraction": summary.get("valid_fraction", 0.0), "method": (files_meta or {}).get("method", "")}
    for k in ("drift", "drift_before_dn", "drift_residual_dn", "normal_mean_error_deg"):
        if k in summary:
            meta_n[k] = summary[k]
    if job.region is not None:
        meta_n["region_pixels"] = int(job.region.sum())
    if job.markers is not None:
        meta_n["markers"] = int(job.markers.sum())
    metas = {"normals": meta_n, "depth": {k: summary[k] for k in ("depth_rmse_mm",) if k in summary},
             "contact": {k: summary[k] for k in ("contact_fraction",) if k in summary}}
    for name, sf in todo.items():
        sf.finish(metas[name])
        job.entries[name]["done"] = True
    return summary


def _partial_exists(path) -> bool:
    from pipeline.base.streamed import partial_path

    return partial_path(path).is_file()


def _summary(job: StreamJob, stats: dict[int, dict]) -> dict:
    out: dict[str, Any] = {}
    H, W = job.shape
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


def link_outputs(job: StreamJob, out) -> list[Path]:
    """``out/normals.h5``, ``out/depth.h5`` (and ``out/contact.h5``): links to the job's store
    entries (:func:`pipeline.outputs.link_results`), never a second copy."""
    from pipeline.outputs import link_results

    return link_results(Path(out), {name: e["path"] for name, e in job.entries.items()})


def reconstruct_stream(capture, *, threads: int | None = 1, progress=None, **options) -> tuple[StreamJob, dict]:
    """Plan, run every missing frame in this process, finish: ``(job, summary)`` (see the module
    docstring; ``options`` as :func:`plan_stream`)."""
    job, cap, lights = plan_stream(capture, **options)
    run = {"frames": 0, "solved": 0, "method": "cached"}
    if not job.cached:
        pipe = prepare(job, cap, lights, threads)
        run = run_frames(job, threads=threads, progress=progress, cap=cap, lights=lights, pipe=pipe)
    summary = finish_stream(job, run) if any(not e["done"] for e in job.entries.values()) else {}
    summary["frames_solved"] = run["solved"]
    summary["method"] = run["method"]
    return job, summary
