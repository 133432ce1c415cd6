"""The files of a streamed reconstruction: partial files opened (or resumed), finished with their
summaries, and linked into an ``--out`` folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.base.errors import UserError
from pipeline.frame_pipeline.outputs import OutputSpec
from pipeline.streaming.job import StreamJob

__all__ = ["open_files", "open_ranges", "finish_stream", "link_outputs"]


def open_files(job: StreamJob) -> dict:
    """The partial files of the entries still to write: created, or opened to resume
    (:class:`pipeline.base.streamed.StreamedFile`). An entry another job of the same work
    finished meanwhile (its file in place, no partial file left) is marked done instead, unless
    the job was asked to rewrite it (``force``)."""
    from pipeline.base.streamed import StreamedFile, partial_path

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
        if not e["done"] and not e.get("force") and Path(e["path"]).is_file() and not partial_path(e["path"]).is_file():
            e["done"] = True
        if e["done"]:
            continue
        schema, datasets, meta = layouts[name]
        static = {}
        if name == "normals" and job.markers is not None:
            static["filled"] = job.filled
        out[name] = StreamedFile.open(e["path"], schema, job.frames, datasets, static=static, meta=meta, key=e["key"])
    return out


def open_ranges(job: StreamJob, start: int | None = None, stop: int | None = None) -> tuple[dict, list]:
    """``(files, ranges)``: :func:`open_files`, and the frame ranges within ``start:stop`` that any of
    them misses."""
    from pipeline.base.streamed import merge_ranges

    files = open_files(job)
    missing = merge_ranges(r for sf in files.values() for r in sf.missing())
    lo = 0 if start is None else int(start)
    hi = max((sf.frames for sf in files.values()), default=0) if stop is None else int(stop)
    return files, [(max(a, lo), min(b, hi)) for a, b in missing if min(b, hi) > max(a, lo)]


def finish_stream(job: StreamJob, files_meta: dict | None = None) -> dict:
    """Summaries into the unfinished entries' attributes, the entries renamed into place. Returns
    the summary (``valid_fraction``, ``drift``, truth errors, ``contact_fraction``)."""
    stats: dict[int, dict] = {}
    todo = open_files(job)
    for sf in todo.values():
        for k, v in sf.stats().items():
            stats.setdefault(k, {}).update(v)
    if todo and len(stats) < job.frames:
        raise UserError(f"{job.capture}: {job.frames - len(stats)} of {job.frames} frames have no results yet")
    summary: dict[str, Any] = job.summarize(stats)
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


def link_outputs(job: StreamJob, out) -> list[Path]:
    """``out/normals.h5``, ``out/depth.h5`` (and ``out/contact.h5``): links to the job's store
    entries (:func:`pipeline.results.exports.link_results`), never a second copy."""
    from pipeline.results.exports import link_results

    return link_results(Path(out), {name: e["path"] for name, e in job.entries.items()})
