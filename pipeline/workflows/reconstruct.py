"""``iristac reconstruct``: normals and depth of a capture, through the stage store, a chunk at a time.

:func:`reconstruct` reads the capture (its frames a chunk at a time) and the light model (a
calibration or an illumination file, or lights embedded in the capture by an importer;
:func:`pipeline.solving.light_files.capture_lights`) and writes the ``normals`` and ``depth`` stage
entries (and the ``contact`` mask's) in one pass over the frames (:mod:`pipeline.streaming`: the
frame pipeline live uses, under the keys the stages compute, so a repeated call, or work
``iristac run`` or ``iristac batch`` already did, is a cache hit). The output folder gets links
to those entries (``normals.h5``, ``depth.h5``, ``contact.h5``) and, with ``images``, a
normal-map PNG, a colour-mapped depth PNG, a PLY point cloud and a contact-mask PNG per
contact instance; the contact mask (:func:`pipeline.frame_pipeline.contact.contact_mask`: the colour change
against the reference and the height) is also :attr:`ReconstructResult.contact`.

Where to solve: the capture's ``mask`` dataset (an object's silhouette, e.g. DiLiGenT's), or a
user's ``mask=`` (a PNG/NPY file or an array), which replaces it
(:func:`pipeline.solving.regions.capture_region`). Only those pixels are solved and integrated
(rectangular integrators on the mask's bounding box); every pixel outside is invalid in the
outputs (:mod:`pipeline.normals.masking`).

Printed gel markers (``markers=``, ``--markers auto|none|MASK.png``; default the capture's own
``markers`` dataset, else the calibration's): filled in before the normals are solved, False
in the normals' mask, integrated through by the depth stage
(:func:`pipeline.solving.regions.marker_mask`).

Illumination drift (``drift=``, ``--drift auto|none|offset|gain_offset|field``): each contact
instance's drift against the no-contact reference (a per-channel gain and offset fitted on the
pixels outside the contact, :mod:`pipeline.normals.drift`) is removed before the solve where
the solver keys on that reference (``auto``, the default: the calibration's models and
``--ratio``), and before the contact mask's colour change always (:mod:`pipeline.frame_pipeline.contact`; its
no-contact frame is the capture's, else the one the solver's model stores).

What is written (``save=``, ``precision=``: :mod:`pipeline.frame_pipeline.outputs`) is part of
the keys.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["ReconstructResult", "reconstruct"]


@dataclass
class ReconstructResult:
    """What :func:`reconstruct` produced.

    ``summary`` has the CLI's JSON keys: ``solver``, ``integrator``, ``seconds``,
    ``valid_fraction`` and, when the capture has ground truth, ``normal_mean_error_deg`` and
    ``depth_rmse_mm`` (means over contact instances); plus ``cached``, ``markers`` (marker
    pixels filled in), ``drift`` (the drift model removed before the solve, ``none`` if none),
    ``contact_fraction`` (the contact mask's share of the image, mean over contact instances)
    and ``outputs``.
    """

    normals: Any
    depth: Any
    summary: dict[str, Any]
    files: list[Path] = field(default_factory=list)
    #: Where the object touches the gel, ``(K, H, W)`` bool (:func:`pipeline.frame_pipeline.contact.contact_mask`).
    contact: Any = None


def reconstruct(capture, *, calibration=None, illumination=None, solver: str | None = None, integrator: str = "dst",
                out=None, store=None, ratio: bool = False, max_condition: float = 1e3, device="cpu",
                dtype="float32", threads: int | None = 1, images: bool = True, force: bool = False,
                compile: bool = False, heal: bool = True, mask=None, markers=None, drift: str = "auto",
                save: str | None = None, precision: str = "single", progress=None, reference=None,
                mm_per_px: float | None = None, profile=None, match_colours: bool | None = None) -> ReconstructResult:
    """Normals and depth of a capture, through the stage store, a chunk of frames at a time.

    Parameters
    ----------
    capture : path or Record
        ``capture.h5`` (a record in memory must carry its path), or a video file (``.mp4``, ``.avi``, ...).
    calibration, illumination : path or Record, optional
        The light model (at most one; see :func:`pipeline.solving.light_files.capture_lights`).
    solver : str, optional
        A name in :data:`pipeline.base.registry.SOLVERS` (``iristac reconstruct --help`` lists
        them all); default ``lstsq``, or the shipped calibration's model (``mlp``) with ``profile``.
    integrator : str
        A name in :data:`pipeline.base.registry.INTEGRATORS` (``fc``, ``dct``, ``dst``, ``sparse``).
    out : path, optional
        Folder for ``normals.h5``, ``depth.h5`` and ``contact.h5`` (links to the store's entries,
        :func:`pipeline.streaming.files.link_outputs`) and, with ``images``, per contact instance
        ``normals_kNNN.png``, ``depth_kNNN.png``, ``depth_kNNN.ply`` and ``contact_kNNN.png``.
    store : StageStore or path, optional
        The stage store (default: ``$IRISTAC_CACHE`` or ``./iristac-cache``).
    ratio : bool
        Divide by the no-contact reference first.
    max_condition : float
        Pixels with a worse-conditioned light matrix are masked.
    device, dtype, threads
        Torch device and dtype of the eager solvers; ``threads``: the frame pipeline's threads
        (:class:`pipeline.frame_pipeline.FramePipeline`: frames in parallel where the solver has
        a fast path, else torch's or BLAS's threads; None: every core). The fast paths equal
        the eager solvers to float rounding, so neither enters the key.
    force : bool
        Recompute even if the store has the results.
    compile : bool
        ``lstsq`` only: solve with the ``torch.compile``-d far-field kernel
        (:mod:`pipeline.normals.fused`). Not part of the cache key.
    heal : bool
        A corrupt or schema-violating cache entry is quarantined, reported in one warning
        line and recomputed (False: it is an error, as ``--no-heal``).
    mask : path or ndarray, shape (H, W), optional
        Reconstruct only these pixels (a ``.png``/``.npy`` file, non-zero inside, or an array),
        instead of the capture's own ``mask`` dataset (or every pixel when it has none).
    markers : None, "auto", "none", path or ndarray (H, W), optional
        Printed gel markers to fill in (:func:`pipeline.solving.regions.marker_mask`); None: the
        capture's own ``markers``, else the calibration's.
    drift : str
        Illumination drift removed before the solve: ``auto`` (default: a per-channel gain and
        offset against the no-contact reference where the solver keys on it: ``far``, ``near``,
        ``traced``, ``lut``, ``mlp`` and ``ratio``), ``none``, ``offset``, ``gain_offset`` or
        ``field``. Part of the cache key.
    save, precision : str
        What is written besides the normals, the heights and their masks, and the normals'
        precision (:class:`pipeline.frame_pipeline.outputs.OutputSpec`; default ``confidence,contact``,
        ``single``). Part of the keys.
    progress : callable, optional
        ``progress(frames)`` after every chunk.
    reference, mm_per_px : optional
        A video file's no-contact frame (an index, default 0, or ``"build"``) and pixel pitch
        (default: the light model's, else the profile's): :func:`pipeline.capture.video_frames.video_capture`.
    profile : str or SensorProfile, optional
        The capture's sensor (a built-in name or a ``.yaml``): its images must be of its size;
        with no light model given, the calibration it ships with is used (:mod:`pipeline.capture.shipped`).
    match_colours : bool, optional
        Bring the frames to the light model's colours by one gain per channel from the no-contact
        frames (:func:`pipeline.streaming.plan.colour_gain_for`), a chunk at a time; the gain is
        ``summary["colour_gain"]`` and in the normals' key. Default: on with a shipped calibration.

    Returns
    -------
    ReconstructResult
    """
    from pipeline.base.store import read_record
    from pipeline.frame_pipeline.outputs import OutputSpec
    from pipeline.streaming.job import LAZY_BYTES
    from pipeline.streaming.local import reconstruct_stream

    t0 = time.perf_counter()
    outputs = OutputSpec.parse(save, precision)
    shipped, mm_per_px = _with_profile(capture, profile, calibration, illumination, mm_per_px)
    calibration, solver, match_colours = _light_model(shipped, calibration, solver, match_colours)
    job, streamed = reconstruct_stream(
        capture, threads=threads, progress=progress, calibration=calibration, illumination=illumination, solver=solver,
        integrator=integrator, store=store, ratio=ratio, max_condition=max_condition, device=device, dtype=dtype,
        compile=compile, mask=mask, markers=markers, drift=drift, outputs=outputs, force=force, heal=heal,
        video={"reference": reference, "mm_per_px": mm_per_px}, match_colours=match_colours)
    recs = {name: read_record(e["path"], e["key"].schema, lazy_bytes=LAZY_BYTES) for name, e in job.entries.items()}
    summary = _summary(job, recs, streamed, solver, integrator)
    summary.update({} if shipped is None else {"shipped_calibration": str(shipped)})
    files: list[Path] = []
    if out is not None:
        files = _write_out(job, recs, Path(out), images)
        summary["outputs"] = [str(f) for f in files]
    summary["seconds"] = round(time.perf_counter() - t0, 4)
    contact = recs["contact"].data["contact"] if "contact" in recs else None
    n_rec, d_rec = recs["normals"], recs["depth"]
    return ReconstructResult(normals=n_rec, depth=d_rec, summary=summary, files=files, contact=contact)


def _light_model(shipped, calibration, solver, match_colours) -> tuple:
    """``(calibration, solver, match_colours)``: a shipped calibration is solved with its own model
    (where no solver is given) and the capture's colours matched to it (where not said otherwise)."""
    from pipeline.capture.shipped import SHIPPED_SOLVER

    if shipped is None:
        return calibration, solver or "lstsq", bool(match_colours)
    return shipped, solver or SHIPPED_SOLVER, True if match_colours is None else bool(match_colours)


def _with_profile(capture, profile, calibration, illumination, mm_per_px):
    """``(shipped calibration or None, mm_per_px)`` of a capture from ``profile`` (None: as given): its images must
    be of the profile's size; without a light model of the user's, the calibration the profile
    ships with (None when it ships none: the capture's own lights, as without a profile); a
    video's pitch, when not given, the profile's."""
    from pipeline.base.errors import UserError
    from pipeline.base.store import Record, describe_file
    from pipeline.capture.sensor_profiles import load_profile
    from pipeline.capture.shipped import shipped_calibration_path
    from pipeline.capture.video_frames import is_video, video_frame_count

    if profile is None:
        return None, mm_per_px
    prof = load_profile(profile)
    video = not isinstance(capture, Record) and is_video(capture)
    if video:
        h, w = video_frame_count(capture)[1]
    else:
        shape = (capture.data["frames"].shape if isinstance(capture, Record) else
                 describe_file(capture)[0]["datasets"].get("frames", {}).get("shape")) or [0] * 5
        h, w = shape[2], shape[3]
    if (w, h) != prof.resolution:
        raise UserError(f"{capture}: images are {w} x {h} px, sensor profile {prof.name!r} is for "
                        f"{prof.resolution[0]} x {prof.resolution[1]} (import the frames with iristac import images SOURCE "
                        f"--profile {prof.name} --out CAPTURE.h5)")
    shipped = shipped_calibration_path(prof) if calibration is None and illumination is None else None
    return shipped, mm_per_px if mm_per_px is not None or not video else prof.mm_per_px


def _summary(job, recs: dict, streamed: dict, solver: str, integrator: str) -> dict[str, Any]:
    """What :attr:`ReconstructResult.summary` says of a run (its records and what the stream measured)."""
    n_rec, d_rec = recs["normals"], recs["depth"]
    summary: dict[str, Any] = {"solver": solver, "integrator": integrator, "seconds": 0.0,
                               "valid_fraction": float(n_rec.meta.get("valid_fraction", 0.0)),
                               "cached": streamed["frames_solved"] == 0,
                               "markers": 0 if job.markers is None else int(job.markers.sum()),
                               "drift": str(n_rec.meta.get("drift", "none")), "frames": job.frames,
                               "method": streamed["method"]}
    summary.update(_truth(job, n_rec, d_rec, streamed))
    if "contact" in recs:
        summary["contact_fraction"] = float(recs["contact"].meta.get("contact_fraction", 0.0))
    if job.options.get("colour_gain") is not None:
        summary["colour_gain"] = list(job.options["colour_gain"])
    return summary


def _write_out(job, recs: dict, out: Path, images: bool) -> list[Path]:
    """The ``--out`` folder: links to the entries and, with ``images``, the pictures of every contact."""
    from pipeline.results.exports import write_pictures
    from pipeline.streaming.files import link_outputs

    files = link_outputs(job, out)
    if images:
        contact = recs["contact"].data["contact"] if "contact" in recs else None
        files += write_pictures(out, recs["normals"], recs["depth"], job.mm_per_px, contact)
    return files


def _truth(job, n_rec, d_rec, streamed: dict) -> dict:
    """Errors against the capture's truth: what the stream measured, what the entries recorded,
    else measured now from the entries (results another command computed)."""
    out = {k: streamed[k] for k in ("normal_mean_error_deg", "depth_rmse_mm") if k in streamed}
    for k, rec in (("normal_mean_error_deg", n_rec), ("depth_rmse_mm", d_rec)):
        if k not in out and k in rec.meta:
            out[k] = float(rec.meta[k])
    if len(out) < 2 and job.video is None:  # a video has no truth
        from pipeline.results.evaluate import truth_errors
        from pipeline.streaming.inputs import read_capture

        cap = read_capture(job.capture)
        if any(k in cap.data for k in ("truth/normals", "truth/height")):
            full = truth_errors(cap, n_rec, d_rec, job.region)
            out = {**full, **out}
    return out
