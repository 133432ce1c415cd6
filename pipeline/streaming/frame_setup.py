"""The frame pipeline a streamed reconstruction runs: the solver, the integrator and the contact mask
its job asks for, on the CPU's threads or a device."""

from __future__ import annotations

import numpy as np

from pipeline.streaming.job import DEVICE_CHUNK, StreamJob

__all__ = ["prepare"]


def _pipeline(job: StreamJob, cap, lights, threads):
    """The :class:`~pipeline.frame_pipeline.FramePipeline` of ``job`` on ``threads`` threads."""
    from pipeline.depth import frame_integrator
    from pipeline.frame_pipeline import FramePipeline
    from pipeline.normals.drift import STREAM_SAMPLES
    from pipeline.solving.frame_solvers import frame_solver
    from pipeline.solving.regions import reference_frames

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
    # The contact mask first: it reads the reference the solver's model stores, before the solver is built.
    contact = _contact_fn(job, cap, lights) if job.outputs.contact and not job.entries["contact"]["done"] else None
    solver = frame_solver(o["solver"], lights, shape=(H, W), channels=frames.shape[-1],
                          reference=reference_frames(cap), dark=cap.data.get("dark"), markers=job.markers,
                          max_condition=o["max_condition"], region=job.region, drift=o["drift"],
                          drift_samples=STREAM_SAMPLES, drift_every=1, raw_dtype=frames.dtype,
                          bit_depth=cap.meta.get("bit_depth"), name=str(cap.path or "capture"), ratio=o["ratio"],
                          device=o["device"], dtype=o["dtype"], compile=o["compile"])
    integ = frame_integrator(o["integrator"], (H, W), job.mm_per_px)
    return FramePipeline(solver, integ, threads=threads, region=job.region, filled=job.filled, contact=contact,
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
    """``contact(frames, height, valid)`` of one frame set (:func:`pipeline.frame_pipeline.contact.contact_mask`),
    against the capture's reference, else the one the solver's model stores, else the height alone."""
    from pipeline.frame_pipeline.contact import contact_mask, contact_reference_level, drift_estimator
    from pipeline.solving.regions import reference_frames

    ref = reference_frames(cap)
    if ref is None:
        ref = lights.stored_reference(job.options["solver"])
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
        from pipeline.streaming.inputs import job_frames

        probe = pipe.run(job_frames(job, np.asarray(cap.data["frames"][0:1])))
        job.meta["groups"] = int(probe.extras["albedo"].shape[-1]) if "albedo" in probe.extras else 1
        job.meta["confidence"] = probe.confidence is not None
        # What the solver says of itself (its method, what its confidence measures): the record's.
        skip = ("drift", "drift_before_dn", "drift_residual_dn", "solver", "max_condition", "ratio")
        job.meta["solver_meta"] = {k: v for k, v in probe.meta[0].items() if k not in skip}
    pipe.extras = job.outputs.normal_extras  # the probe's albedo was only to learn its groups
    job.meta.setdefault("lights", lights.source)
    return pipe
