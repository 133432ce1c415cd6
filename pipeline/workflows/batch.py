"""``iristac batch``: reconstruct recordings of any length with one shared light model.

Each recording is planned here (:func:`pipeline.streaming.plan.plan_stream`: its keys, what the store
already has; a bad recording is reported and skipped, the others go on), then its missing
frames are reconstructed by the one frame pipeline a chunk at a time (:func:`pipeline.streaming.frames.run_frames`):

- in this process, frames in parallel on ``threads`` threads (the default);
- on ``workers`` local processes or a Dask cluster (``scheduler``): every recording's missing
  frames cut into frame ranges (a long recording is many tasks, not one), each range written
  straight into the recording's partial store files by the worker that solved it. Video files
  (:mod:`pipeline.capture.video_frames`: decoded in order from their start) run in this process.

Memory does not grow with a recording's length; a run killed at any moment resumes from the
chunks its progress files record; a rerun of finished work is read from the store. Results
equal a serial run's whatever ran them (the same code on the same frames; a task's result
holds only what the inputs decide). Timings and memory live in the summary
(:func:`summary_json`).

Examples
--------
>>> import tempfile, os
>>> from sim.render import bare_ring_illumination
>>> from sim.rendered_capture import render_capture
>>> from pipeline.base.capture import write_capture
>>> from pipeline.stages.synthesize import illumination_record
>>> from sim.contacts import contact_surfaces
>>> from pipeline.base.store import write_record
>>> d = tempfile.mkdtemp()
>>> model = bare_ring_illumination((12, 16), 0.5)
>>> ill = str(write_record(os.path.join(d, "ill.h5"), illumination_record(model)))
>>> rec = os.path.join(d, "rec.h5")
>>> surfaces = contact_surfaces("sphere", (12, 16), 0.5, 2, size_mm=1.5)
>>> _ = write_capture(rec, render_capture(model, "monochromatic", surfaces))
>>> items = batch_reconstruct([rec], illumination=ill, solver="nearfield", store=os.path.join(d, "cache"))
>>> r = items[0].result
>>> items[0].ok, r["contacts"], r["normal_mean_error_deg"] < 5, len(r["depth_sha256"])
(True, 2, True, 32)
"""

from __future__ import annotations

import resource
import time
from pathlib import Path
from typing import Any, Sequence

from pipeline.base.errors import UserError
from pipeline.workflows.task_pool import BatchItem, error_message, map_tasks

__all__ = ["batch_reconstruct", "expand_recordings", "summary_json", "SUMMARY_COLUMNS", "frame_ranges"]

#: The fewest frames a worker's range holds (each range pays the solver's set-up once).
MIN_RANGE = 16

#: Result keys shown in the summary table.
SUMMARY_COLUMNS = ("frames", "valid_fraction", "normal_mean_error_deg", "depth_rmse_mm")


def expand_recordings(paths: Sequence[str]) -> list[str]:
    """Files as given; folders become their ``*.h5`` files and videos (by suffix), sorted.

    Raises
    ------
    UserError
        A path that does not exist, or nothing to process.
    """
    from pipeline.capture.video_frames import is_video

    out: list[str] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += [str(f) for f in sorted(p.iterdir()) if f.is_file() and (f.suffix == ".h5" or is_video(f))]
        elif p.exists():
            out.append(str(p))
        else:
            raise UserError(f"{p}: no such recording (expected a capture.h5, a video or a folder of them)")
    if not out:
        raise UserError(f"no recordings to process in {', '.join(map(str, paths)) or '(none given)'}")
    return out


def frame_ranges(missing: Sequence[tuple[int, int]], parts: int, min_frames: int) -> list[tuple[int, int]]:
    """The ``missing`` frame ranges cut into about ``parts`` pieces of at least ``min_frames``.

    >>> frame_ranges([(0, 100)], 4, 10)
    [(0, 25), (25, 50), (50, 75), (75, 100)]
    >>> frame_ranges([(0, 30), (50, 60)], 8, 16)
    [(0, 15), (15, 30), (50, 60)]
    """
    total = sum(b - a for a, b in missing)
    size = max(int(min_frames), -(-total // max(1, int(parts))))
    out = []
    for a, b in missing:
        n = max(1, round((b - a) / size))
        step = -(-(b - a) // n)
        out += [(s, min(b, s + step)) for s in range(a, b, step)]
    return out


#: What a worker process set up for a job (its capture and frame pipeline), kept for
#: the job's next range: a worker takes several ranges of a recording, and the set-up (reading the
#: light model, the solver's precomputation) is the same for each.
_WORKER_JOBS: dict = {}


def _range_task(job, start: int, stop: int, threads) -> dict:
    """A worker's frame range (module level: picklable for a process pool and Dask)."""
    from pipeline.solving.light_files import capture_lights
    from pipeline.streaming.frame_setup import prepare
    from pipeline.streaming.frames import run_frames
    from pipeline.streaming.inputs import job_capture, load_light_record

    ident = (job.capture, tuple(e["key"].digest for e in job.entries.values()), threads)
    if ident not in _WORKER_JOBS:
        cap = job_capture(job)
        lights = capture_lights(cap, load_light_record(job.light_files["calibration"], "calibration"),
                                load_light_record(job.light_files["illumination"], "illumination"))
        for _, old_pipe in _WORKER_JOBS.values():  # one job's set-up at a time per worker
            old_pipe.close()
        _WORKER_JOBS.clear()
        _WORKER_JOBS[ident] = (cap, prepare(job, cap, lights, threads))
    cap, pipe = _WORKER_JOBS[ident]
    return run_frames(job, start, stop, threads=threads, cap=cap, pipe=pipe, keep=True)


def batch_reconstruct(recordings: Sequence[str], *, calibration: str | None = None, illumination: str | None = None,
                      solver: str = "lstsq", integrator: str = "dst", out: str | None = None,
                      store: str | None = None, images: bool = False, device: str = "cpu", workers: int = 1,
                      scheduler: str | None = None, progress: bool = False, connect_timeout: float = 10.0,
                      heal: bool = True, mask: str | None = None, markers: str | None = None,
                      threads: int | None = 1, drift: str = "auto", save: str | None = None,
                      precision: str = "single", force: bool = False, reference=None,
                      mm_per_px: float | None = None, match_colours: bool = False) -> list[BatchItem]:
    """Reconstruct every recording with a shared calibration or illumination model.

    Parameters
    ----------
    recordings : sequence of str
        ``capture.h5`` files, video files or folders of them (:func:`expand_recordings`).
    calibration, illumination : str, optional
        The shared light model (at most one).
    solver, integrator, device, heal, mask, markers, drift, force
        As :func:`pipeline.workflows.reconstruct.reconstruct`.
    out : str, optional
        ``out/<recording stem>/normals.h5``, ``depth.h5`` (and ``contact.h5``): links to the
        store's entries; with ``images`` also the per-instance pictures.
    store : str, optional
        Stage store folder (default ``$IRISTAC_CACHE`` or ``./iristac-cache``): workers must see it.
    workers : int
        Local processes (1: this process).
    scheduler : str, optional
        A Dask scheduler address (``tcp://host:8786``): frame ranges spread over its workers,
        which must see the same paths (and the store) as this machine.
    threads : int, optional
        The frame pipeline's threads in each process (None: every core).
    save, precision : str
        What is written (:class:`pipeline.frame_pipeline.outputs.OutputSpec`; default
        :data:`~pipeline.frame_pipeline.outputs.DEFAULT_BATCH`: the normals and heights with their
        masks), float type.
    progress : bool
        A progress bar of frames on stderr (frames, frames/s, time left).
    reference, mm_per_px : optional
        Videos' no-contact frame (an index, default 0, or ``"build"``) and pixel pitch (default:
        the light model's): :func:`pipeline.capture.video_frames.video_capture`. A video's frames
        are decoded in order, so a video runs in this process even with ``workers`` or
        ``scheduler`` (frames in parallel on ``threads``).
    match_colours : bool
        Bring each recording's frames to the light model's colours by one gain per channel from
        its own no-contact frames (recordings of other units, or of one unit whose LEDs aged), as
        :func:`pipeline.workflows.reconstruct.reconstruct` does: the same entries.

    Returns
    -------
    list of pipeline.workflows.task_pool.BatchItem
        One per recording, in input order.
    """
    from pipeline.frame_pipeline.outputs import DEFAULT_BATCH, OutputSpec

    if calibration is not None and illumination is not None:
        raise UserError("batch: give either --calibration or --illumination, not both")
    if workers < 1:
        raise UserError(f"--workers must be at least 1, got {workers}")
    marker_file = markers if markers not in (None, "auto", "none") else None
    for flag, path in (("--calibration", calibration), ("--illumination", illumination), ("--mask", mask),
                       ("--markers", marker_file)):
        if path is not None and not Path(path).is_file():
            raise UserError(f"{flag} {path}: no such file")
    outputs = OutputSpec.parse(DEFAULT_BATCH if save is None else save, precision)
    recs = [str(Path(r).resolve()) for r in expand_recordings(recordings)]
    if store is None:
        from pipeline.base.store import default_store_root

        store = str(default_store_root())
    store = str(Path(store).resolve())
    options = dict(calibration=_absolute(calibration), illumination=_absolute(illumination), solver=solver,
                   integrator=integrator, store=store, device=device, mask=_absolute(mask),
                   markers=_absolute(marker_file) if marker_file else markers, drift=drift, outputs=outputs,
                   heal=heal, force=force, video={"reference": reference, "mm_per_px": mm_per_px},
                   match_colours=bool(match_colours))
    t0 = time.perf_counter()
    planned = [_plan(r, options, threads) for r in recs]
    todo = sum(p["frames"] for p in planned if p.get("job") is not None and not p["job"].cached)
    bar = _bar(todo, progress)
    try:
        if scheduler or workers > 1:
            _run_distributed(planned, threads, workers, scheduler, connect_timeout, bar)
        else:
            for p in planned:
                _run_here(p, threads, bar)
    finally:
        bar.close()
    return [_finish(p, out, images, t0) for p in planned]


def _absolute(p):
    return None if p is None else str(Path(p).resolve())


def _plan(recording: str, options: dict, threads) -> dict:
    """A recording's job, or its failure (one bad recording never stops the batch)."""
    from pipeline.streaming.frame_setup import prepare
    from pipeline.streaming.plan import plan_stream

    t0 = time.perf_counter()
    entry: dict[str, Any] = {"recording": recording, "job": None, "error": None, "frames": 0, "t0": t0,
                             "method": "cached", "pipe": None}
    try:
        job, cap, lights = plan_stream(recording, **options)
        entry.update(job=job, frames=job.frames, cap=cap)
        if not job.cached:
            entry["pipe"] = prepare(job, cap, lights, threads)
    except Exception as exc:  # noqa: BLE001 - reported in its item
        entry["error"] = error_message(exc)
    entry["seconds"] = time.perf_counter() - t0
    return entry


def _run_here(p: dict, threads, bar) -> None:
    from pipeline.streaming.frames import run_frames

    job = p["job"]
    if job is None or job.cached or p["error"]:
        return
    t0 = time.perf_counter()
    try:
        r = run_frames(job, threads=threads, progress=bar.update, cap=p["cap"], pipe=p["pipe"])
        p["method"], p["workers"], p["frames_solved"] = r["method"], {r["worker"]}, r["solved"]
    except Exception as exc:  # noqa: BLE001 - this recording fails, the others go on
        p["error"] = error_message(exc)
    p["solve_seconds"] = time.perf_counter() - t0
    p["seconds"] += p["solve_seconds"]


def _run_distributed(planned: list[dict], threads, workers: int, scheduler, connect_timeout: float, bar) -> None:
    """Every recording's missing frames as frame ranges on a process pool or a Dask cluster."""
    from pipeline.streaming.files import open_files

    tasks, owners = [], []
    parts = max(2, workers) * 2
    for i, p in enumerate(planned):
        job = p["job"]
        if job is None or job.cached or p["error"]:
            continue
        if job.video is not None:  # decoded in order from its start: run here, not cut into ranges
            _run_here(p, threads, bar)
            continue
        p.pop("pipe", None)  # the workers build their own
        try:
            files = open_files(job)  # created here once, so the workers only attach to them
        except Exception as exc:  # noqa: BLE001
            p["error"] = error_message(exc)
            continue
        from pipeline.base.streamed import merge_ranges

        missing = merge_ranges(r for sf in files.values() for r in sf.missing())
        for a, b in frame_ranges(missing, parts, MIN_RANGE):
            tasks.append((job, a, b, threads))
            owners.append(i)
    t0 = time.perf_counter()
    results = map_tasks(_range_task, tasks, workers=workers, scheduler=scheduler, connect_timeout=connect_timeout,
                        on_done=lambda k: bar.update(tasks[k][2] - tasks[k][1]))
    busy: dict[str, float] = {}  # per worker: its ranges' seconds, first frame read to last result on disk
    for k, (ok, value) in enumerate(results):
        p = planned[owners[k]]
        if ok:
            p["method"] = value["method"]
            p.setdefault("workers", set()).add(value["worker"])
            p["frames_solved"] = p.get("frames_solved", 0) + value["solved"]
            busy[value["worker"]] = busy.get(value["worker"], 0.0) + value["seconds"]
        elif not p["error"]:
            p["error"] = value
    seconds = time.perf_counter() - t0
    # The solving time is the busiest worker's, as a thread's excludes the start-up: the workers'
    # own start-up (spawning, imports, set-up) is in ``seconds`` and the summary's start-up.
    solving = min(seconds, max(busy.values(), default=seconds))
    ranged = [q for q in planned if q["job"] is not None and q["job"].video is None]  # videos timed by _run_here
    total = max(1, sum(q.get("frames_solved", 0) for q in ranged))
    for p in ranged:
        p["seconds"] += seconds * p.get("frames_solved", 0) / total
        p["solve_seconds"] = solving * p.get("frames_solved", 0) / total


def _finish(p: dict, out, images: bool, t0: float) -> BatchItem:
    """The item of one recording: its entries finished and summarised, linked into ``out``."""
    from pipeline.base.store import read_record
    from pipeline.streaming.files import finish_stream, link_outputs
    from pipeline.streaming.job import LAZY_BYTES

    job = p["job"]
    if p["error"] or job is None:
        return BatchItem(p["recording"], False, p["seconds"], None, p["error"])
    try:
        summary = finish_stream(job, {"method": p["method"]})
        recs = {name: read_record(e["path"], e["key"].schema, lazy_bytes=LAZY_BYTES)
                for name, e in job.entries.items()}
        n_meta, d_meta = recs["normals"].meta, recs["depth"].meta
        result: dict[str, Any] = {
            "normals_key": job.entries["normals"]["key"].digest, "depth_key": job.entries["depth"]["key"].digest,
            "normals_sha256": str(n_meta.get("stream_digest") or _content_digest(recs["normals"], "normals")),
            "depth_sha256": str(d_meta.get("stream_digest") or _content_digest(recs["depth"], "height")),
            "contacts": job.frames, "frames": job.frames, "valid_fraction": float(n_meta.get("valid_fraction", 0.0)),
            "outputs": []}
        for k, meta in (("normal_mean_error_deg", n_meta), ("depth_rmse_mm", d_meta)):
            if k in summary or k in meta:
                result[k] = float(summary.get(k, meta.get(k)))
        if "contact" in recs:
            result["contact_fraction"] = float(recs["contact"].meta.get("contact_fraction", 0.0))
        if out is not None:
            dest = Path(out) / Path(p["recording"]).stem
            files = link_outputs(job, dest)
            if images:
                from pipeline.results.exports import write_pictures

                files += write_pictures(dest, recs["normals"], recs["depth"], job.mm_per_px,
                                        recs["contact"].data["contact"] if "contact" in recs else None)
            result["outputs"] = [str(f) for f in files]
        return BatchItem(p["recording"], True, p["seconds"], result, None, worker=",".join(sorted(p.get("workers", ()))),
                         method=p["method"], frames_solved=int(p.get("frames_solved", 0)),
                         solve_seconds=float(p.get("solve_seconds", 0.0)))
    except Exception as exc:  # noqa: BLE001
        return BatchItem(p["recording"], False, p["seconds"], None, error_message(exc))


def _content_digest(rec, name: str) -> str:
    """A digest of an entry's dataset that was not streamed (written whole by ``iristac run``)."""
    import hashlib

    import numpy as np

    a = np.ascontiguousarray(np.asarray(rec.data[name]))
    return hashlib.sha256(str((a.dtype.str, a.shape)).encode() + a.tobytes()).hexdigest()[:32]


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB): ``VmHWM`` of ``/proc/self/status`` where there is
    one (``ru_maxrss`` survives ``exec``, so a process started by a large one would report its
    parent's peak), else ``ru_maxrss``."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def summary_json(items: Sequence[BatchItem], seconds: float) -> dict:
    """The ``--json`` summary: the items, counts, frames, the run's wall time (``seconds``), the
    frames solved per second from the first frame read to the last result on disk
    (``frames_per_second``; start-up apart: ``startup_seconds``, loading the light model, planning,
    the solvers' precomputation and their compiled code from the disk cache) and the peak resident
    memory of this process (``peak_rss_mb``; of its worker processes: ``peak_rss_workers_mb``)."""
    failed = sum(not i.ok for i in items)
    solved = sum(i.frames_solved for i in items)
    solving = sum(i.solve_seconds for i in items)
    frames = sum(i.result["frames"] for i in items if i.ok)
    return {"items": [i.to_json() for i in items], "processed": len(items) - failed, "failed": failed,
            "frames": frames, "frames_solved": solved, "seconds": round(seconds, 3),
            "solve_seconds": round(solving, 3), "startup_seconds": round(max(0.0, seconds - solving), 3),
            "frames_per_second": round(solved / solving, 2) if solving > 0 and solved else 0.0,
            "peak_rss_mb": round(peak_rss_mb(), 1),
            "peak_rss_workers_mb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0, 1)}


def _bar(total: int, enabled: bool):
    from pipeline.workflows.task_pool import progress_bar

    return progress_bar(total, enabled, unit="frame", desc="batch")
