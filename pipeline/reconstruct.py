"""``iristac reconstruct``: normals and depth of a capture, through the normals and depth stages.

:func:`reconstruct` reads the capture and the light model (a calibration or an illumination
file, or lights embedded in the capture by an importer; :func:`pipeline.stages.normals.capture_lights`),
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

Illumination drift (``drift=``, ``--drift auto|none|offset|gain_offset|field``): each contact
instance's drift against the no-contact reference (a per-channel gain and offset fitted on the
pixels outside the contact, :mod:`pipeline.normals.drift`) is removed before the solve where
the solver keys on that reference (``auto``, the default: the calibration's models and
``--ratio``), and before the contact mask's colour change always (:mod:`pipeline.contact`; its
no-contact frame is the capture's, else the one the solver's model stores).
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
    pixels filled in), ``drift`` (the drift model removed before the solve, ``none`` if none),
    ``contact_fraction`` (the contact mask's share of the image, mean over contact instances)
    and ``outputs``.
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
                compile: bool = False, heal: bool = True, mask=None, markers=None,
                drift: str = "auto") -> ReconstructResult:
    """Normals and depth of a capture, through the stage store.

    Parameters
    ----------
    capture : path or Record
        ``capture.h5``.
    calibration, illumination : path or Record, optional
        The light model (at most one; see :func:`pipeline.stages.normals.capture_lights`).
    solver : str
        A name in :data:`pipeline.base.registry.SOLVERS` (``iristac reconstruct --help`` lists
        them all).
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
        Torch device and dtype of the solvers (``lstsq`` on the CPU computes with numpy and does
        not import torch); torch intra-op threads while solving (BLAS threads for that numpy
        solve: :meth:`pipeline.normals.solve.FrameSolver.thread_limits`), and the
        contact instances the depth stage integrates at once, one per thread (default 1:
        fastest on a small shared CPU; None leaves torch's setting and uses every core). With
        other than one thread on the CPU, ``nearfield``/``lstsq`` on integer frames and ``dst``
        on the whole frame take their batch fast paths (every instance at once, a run of them
        per thread in one compiled call: :mod:`pipeline.normals.cpu_batch`; equal to the eager
        paths to float32 rounding). On a GPU
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
    drift : str
        Illumination drift removed before the solve (:func:`pipeline.stages.normals.compute`):
        ``auto`` (default: a per-channel gain and offset against the no-contact reference where
        the solver keys on it: ``far``, ``near``, ``traced``, ``lut``, ``mlp`` and ``ratio``),
        ``none``, ``offset``, ``gain_offset`` or ``field``. Part of the cache key.

    Returns
    -------
    ReconstructResult
    """
    from pipeline.base.registry import INTEGRATORS, SOLVERS
    from pipeline.base.store import StageStore
    from pipeline.evaluate import truth_errors
    from pipeline.outputs import write_outputs
    from pipeline.stages import capture as capture_stage
    from pipeline.stages import depth as depth_stage
    from pipeline.stages import normals as normals_stage

    SOLVERS.check(solver)
    INTEGRATORS.check(integrator)
    t0 = time.perf_counter()
    cap = _read(capture, "capture")
    cal = None if calibration is None else _read(calibration, "calibration")
    ill = None if illumination is None else _read(illumination, "illumination")
    lights = normals_stage.capture_lights(cap, cal, ill)
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
        heal=heal, mask=user_region, markers=marks, drift=drift)
    d_rec, _, d_cached = depth_stage.run(store, n_rec, n_key, integrator=integrator, force=force, heal=heal,
                                         region=region, device=device, threads=threads)
    seconds = time.perf_counter() - t0
    summary: dict[str, Any] = {"solver": solver, "integrator": integrator, "seconds": round(seconds, 4),
                               "valid_fraction": float(np.asarray(n_rec.data["mask"]).mean()),
                               "cached": bool(n_cached and d_cached),
                               "markers": 0 if marks is None else int(marks.sum()),
                               "drift": str(n_rec.meta.get("drift", "none"))}
    summary.update(truth_errors(cap, n_rec, d_rec, region))
    from pipeline.contact import capture_contact_masks
    from pipeline.normals.solve import stored_reference

    # The colour change against the capture's reference, else the one the solver's model stores
    # (its drift against the frames, a dark level included, is removed before the change is taken).
    ref = normals_stage.reference_frames(cap)
    if ref is None:
        ref = stored_reference(lights, solver)
    frames = cap.data["frames"]
    ref = ref if ref is not None and np.shape(ref) == frames.shape[1:] else None
    contact = capture_contact_masks({"frames": frames, "reference": ref}, d_rec.data["height"], d_rec.data["mask"],
                                    region)
    summary["contact_fraction"] = float(contact.mean()) if contact.size else 0.0
    files: list[Path] = []
    if out is not None:
        files = write_outputs(Path(out), n_rec, d_rec, mm_per_px, images, contact)
        summary["outputs"] = [str(f) for f in files]
    return ReconstructResult(normals=n_rec, depth=d_rec, summary=summary, files=files, contact=contact)
