"""``iristac reconstruct``: normals and depth of a capture, through the normals and depth stages.

:func:`reconstruct` reads the capture and the light model (a calibration or an illumination
file, or lights embedded in the capture by an importer; :func:`pipeline.stages.normals.load_lights`),
then runs the normals stage (:mod:`pipeline.stages.normals`, the solver picked from
:data:`pipeline.base.registry.SOLVERS`) and the depth stage (:mod:`pipeline.stages.depth`)
through the stage store: the same keys ``iristac run`` and ``iristac batch`` use, so a
repeated call, or work ``run`` already did, is a cache hit. It copies both results to the
output folder and writes a normal-map PNG, a colour-mapped depth PNG, a PLY point cloud and a
contact-mask PNG per contact instance; the contact mask (:func:`pipeline.contact.contact_mask`:
the colour change against the reference and the height) is also the ``contact`` dataset of
the output ``depth.h5`` and :attr:`ReconstructResult.contact`.

Where to solve: the capture's ``mask`` dataset (an object's silhouette, e.g. DiLiGenT's), or a
user's ``mask=`` (a PNG/NPY file or an array), which replaces it
(:func:`pipeline.stages.normals.capture_region`). Only those pixels are read out of the
frames, solved and integrated (rectangular integrators on the mask's bounding box); every
pixel outside is invalid in the outputs (:mod:`pipeline.normals.masking`).

Printed gel markers (``markers=``, ``--markers auto|none|MASK.png``; default the capture's own
``markers`` dataset, else the calibration's): filled in before the normals are solved, False
in the normals' mask, integrated through by the depth stage
(:func:`pipeline.stages.normals.marker_mask`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError

__all__ = ["ReconstructResult", "reconstruct"]


@dataclass
class ReconstructResult:
    """What :func:`reconstruct` produced.

    ``summary`` has the CLI's JSON keys: ``solver``, ``integrator``, ``seconds``,
    ``valid_fraction`` and, when the capture has ground truth, ``normal_mean_error_deg`` and
    ``depth_rmse_mm`` (means over contact instances); plus ``cached``, ``markers`` (marker
    pixels filled in), ``contact_fraction`` (the contact mask's share of the image, mean over
    contact instances) and ``outputs``.
    """

    normals: Any
    depth: Any
    summary: dict[str, Any]
    files: list[Path] = field(default_factory=list)
    #: Where the object touches the gel, ``(K, H, W)`` bool (:func:`pipeline.contact.contact_mask`).
    contact: Any = None


def _read(path_or_record, schema: str):
    from pipeline.base.store import Record, read_record

    if isinstance(path_or_record, Record):
        if path_or_record.schema != schema:
            raise UserError(f"expected a {schema!r} record, got {path_or_record.schema!r}")
        return path_or_record
    p = Path(path_or_record)
    if not p.exists():
        raise UserError(f"{p}: {schema} file not found")
    return read_record(p, schema=schema)


def reconstruct(capture, *, calibration=None, illumination=None, solver: str = "lstsq", integrator: str = "dst",
                out=None, store=None, ratio: bool = False, max_condition: float = 1e3, device="cpu",
                dtype="float32", threads: int | None = 1, images: bool = True, force: bool = False,
                compile: bool = False, heal: bool = True, mask=None, markers=None) -> ReconstructResult:
    """Normals and depth of a capture, through the stage store.

    Parameters
    ----------
    capture : path or Record
        ``capture.h5``.
    calibration, illumination : path or Record, optional
        The light model (at most one; see :func:`pipeline.stages.normals.load_lights`).
    solver : str
        A name in :data:`pipeline.base.registry.SOLVERS` (``lstsq``, ``nearfield``, ``robust``,
        ``cauchy``, ``lut``).
    integrator : str
        A name in :data:`pipeline.base.registry.INTEGRATORS` (``fc``, ``dct``, ``dst``, ``sparse``).
    out : path, optional
        Folder for ``normals.h5``, ``depth.h5`` (with ``contact``) and, with ``images``, per
        contact instance ``normals_kNNN.png``, ``depth_kNNN.png``, ``depth_kNNN.ply`` and
        ``contact_kNNN.png``.
    store : StageStore or path, optional
        The stage store (default: ``$IRISTAC_CACHE`` or ``./iristac-cache``).
    ratio : bool
        Divide by the no-contact reference first.
    max_condition : float
        Pixels with a worse-conditioned light matrix are masked.
    device, dtype, threads
        Torch device and dtype of the solvers; torch intra-op threads while solving
        (default 1: fastest on a small shared CPU; None leaves torch's setting). On a GPU
        (``cuda``) ``nearfield`` solves every contact instance as one batch and ``dst``
        integrates them all by FFT on the device (:mod:`pipeline.normals.batched`).
    force : bool
        Recompute even if the store has the results.
    compile : bool
        ``lstsq`` only: solve with the ``torch.compile``-d far-field kernel
        (:mod:`pipeline.normals.fused`): about 4x faster per frame after a few seconds of
        compilation, so worth it for recordings of many frames. Not part of the cache key
        (the results agree with the eager solver to float rounding).
    heal : bool
        A corrupt or schema-violating cache entry is quarantined, reported in one warning
        line and recomputed (False: it is an error, as ``--no-heal``).
    mask : path or ndarray, shape (H, W), optional
        Reconstruct only these pixels (a ``.png``/``.npy`` file, non-zero inside, or an array),
        instead of the capture's own ``mask`` dataset (or every pixel when it has none).
    markers : None, "auto", "none", path or ndarray (H, W), optional
        Printed gel markers to fill in (:func:`pipeline.stages.normals.marker_mask`); None: the
        capture's own ``markers``, else the calibration's.

    Returns
    -------
    ReconstructResult
    """
    from pipeline.base.registry import INTEGRATORS, SOLVERS
    from pipeline.base.store import StageStore
    from pipeline.stages import capture as capture_stage
    from pipeline.stages import depth as depth_stage
    from pipeline.stages import normals as normals_stage

    SOLVERS.check(solver)
    INTEGRATORS.check(integrator)
    t0 = time.perf_counter()
    cap = _read(capture, "capture")
    cal = None if calibration is None else _read(calibration, "calibration")
    ill = None if illumination is None else _read(illumination, "illumination")
    lights = normals_stage.load_lights(cap, cal, ill)
    if ratio and normals_stage.reference_frames(cap) is None:
        raise UserError(f"{cap.path}: --ratio needs no-contact reference frames (dataset 'reference'); this "
                        f"capture has none (source {cap.meta.get('source')!r})")
    region = normals_stage.capture_region(cap, mask)
    marks = normals_stage.marker_mask(cap, markers, lights)
    user_region = None if mask is None else region  # the capture's own mask is part of its identity
    mm_per_px = float(cap.meta["mm_per_px"])
    store = store if isinstance(store, StageStore) else StageStore(store)
    n_rec, n_key, n_cached = normals_stage.run(
        store, cap, capture_stage.capture_key(store, cap), lights, solver=solver, ratio=ratio,
        max_condition=max_condition, device=device, dtype=dtype, threads=threads, compile=compile, force=force,
        heal=heal, mask=user_region, markers=marks)
    d_rec, _, d_cached = depth_stage.run(store, n_rec, n_key, integrator=integrator, force=force, heal=heal,
                                         region=region, device=device)
    seconds = time.perf_counter() - t0
    summary: dict[str, Any] = {"solver": solver, "integrator": integrator, "seconds": round(seconds, 4),
                               "valid_fraction": float(np.asarray(n_rec.data["mask"]).mean()),
                               "cached": bool(n_cached and d_cached),
                               "markers": 0 if marks is None else int(marks.sum())}
    summary.update(_truth_errors(cap, n_rec, d_rec, region))
    from pipeline.contact import capture_contact_masks

    contact = capture_contact_masks(cap.data, d_rec.data["height"], d_rec.data["mask"], region)
    summary["contact_fraction"] = float(contact.mean()) if contact.size else 0.0
    files: list[Path] = []
    if out is not None:
        files = _write_outputs(Path(out), n_rec, d_rec, mm_per_px, images, contact)
        summary["outputs"] = [str(f) for f in files]
    return ReconstructResult(normals=n_rec, depth=d_rec, summary=summary, files=files, contact=contact)


def _truth_errors(cap, n_rec, d_rec, region=None) -> dict:
    """Mean normal error (deg) and depth RMSE (mm) against the capture's truth, if any, over
    ``region`` (the solved mask; None: every pixel)."""
    from pipeline.evaluate import normal_error_stats

    out: dict[str, float] = {}
    if "truth/normals" in cap.data:
        gt = cap.data["truth/normals"]
        errs = []
        for k in range(gt.shape[0]):
            m = np.linalg.norm(gt[k], axis=-1) > 0
            if region is not None:
                m &= np.asarray(region, bool)
            errs.append(normal_error_stats(n_rec.data["normals"][k], gt[k], m)["mean_deg"])
        out["normal_mean_error_deg"] = float(np.mean(errs))
    if "truth/height" in cap.data:
        diff = d_rec.data["height"].astype(np.float64) - cap.data["truth/height"]
        if region is not None:
            diff = diff[:, np.asarray(region, bool)]
        out["depth_rmse_mm"] = float(np.sqrt(np.mean(diff ** 2)))
    return out


def _write_outputs(out: Path, n_rec, d_rec, mm_per_px: float, images: bool, contact) -> list[Path]:
    from pipeline.outputs import normal_map_rgb, write_depth_png, write_normal_png, write_ply, write_png
    from pipeline.base.store import Record, write_record

    out.mkdir(parents=True, exist_ok=True)
    files = [write_record(out / "normals.h5", Record("normals", n_rec.data, n_rec.meta)),
             write_record(out / "depth.h5", Record("depth", {**d_rec.data, "contact": contact}, d_rec.meta))]
    if images:
        for k in range(n_rec.data["normals"].shape[0]):
            n, nm = n_rec.data["normals"][k], n_rec.data["mask"][k]
            h, hm = d_rec.data["height"][k], d_rec.data["mask"][k]
            files.append(write_normal_png(out / f"normals_k{k:03d}.png", n, nm))
            files.append(write_depth_png(out / f"depth_k{k:03d}.png", h, hm))
            files.append(write_ply(out / f"depth_k{k:03d}.ply", h, mm_per_px, hm, colors=normal_map_rgb(n, nm)))
            files.append(write_png(out / f"contact_k{k:03d}.png", np.repeat(contact[k, ..., None] * np.uint8(255), 3, -1)))
    return files
