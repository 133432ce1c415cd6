"""``iristac batch``: reconstruct many recorded captures with one shared light model.

:func:`batch_reconstruct` hands :func:`reconstruct_recording` (a module-level, picklable
task calling :func:`pipeline.reconstruct.reconstruct`) to :func:`pipeline.batch.run_batch`:
serially, on a local process pool (``workers``) or on a Dask cluster (``scheduler``). Every
recording goes through the shared stage store, so a rerun reads results back and workers on
several machines can share a network store (entries are written atomically). One bad
recording is reported and skipped. A task's result holds only what the inputs decide (stage
keys, content digests of the normals and heights, errors against truth), so a parallel run's
results equal a serial run's exactly; timings live in :class:`pipeline.batch.BatchItem`.

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

import hashlib
from functools import partial
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.base.errors import UserError

__all__ = ["reconstruct_recording", "batch_reconstruct", "expand_recordings", "SUMMARY_COLUMNS"]

#: Result keys shown in the summary table.
SUMMARY_COLUMNS = ("valid_fraction", "normal_mean_error_deg", "depth_rmse_mm")


def _sha(a: np.ndarray) -> str:
    a = np.ascontiguousarray(a)
    return hashlib.sha256(str((a.dtype.str, a.shape)).encode() + a.tobytes()).hexdigest()[:32]


def reconstruct_recording(recording: str, *, calibration: str | None = None, illumination: str | None = None,
                          solver: str = "lstsq", integrator: str = "dst", out: str | None = None,
                          store: str | None = None, images: bool = False, device: str = "cpu",
                          heal: bool = True, mask: str | None = None, markers: str | None = None,
                          threads: int | None = 1, drift: str = "auto") -> dict[str, Any]:
    """Reconstruct one recording (the batch task; picklable as a :func:`functools.partial`).

    Parameters
    ----------
    recording : str
        A ``capture.h5``.
    calibration, illumination : str, optional
        The shared light model file (exactly one, unless the capture embeds its lights).
    solver, integrator : str
        As in :func:`pipeline.reconstruct.reconstruct`.
    out : str, optional
        Results go to ``out/<recording stem>/`` (``normals.h5``, ``depth.h5``, and PNG/PLY
        with ``images``).
    store : str, optional
        Stage store folder (default ``$IRISTAC_CACHE`` or ``./iristac-cache``).
    device : str
        Torch device.
    threads : int, optional
        Threads of one recording (:func:`pipeline.reconstruct.reconstruct`'s: torch's while solving,
        contact instances integrated at once); None: every core.
    heal : bool
        Quarantine and recompute a corrupt cache entry (False: the recording fails on it).
    mask : str, optional
        A mask file (PNG/NPY) of the pixels to reconstruct, for every recording (replaces a
        capture's own ``mask``).
    markers : str, optional
        ``auto``, ``none`` or a marker mask image, for every recording (default: each
        capture's own markers, else the calibration's; :func:`pipeline.stages.normals.marker_mask`).
    drift : str
        Illumination drift removed before the solve (:func:`pipeline.reconstruct.reconstruct`'s).

    Returns
    -------
    dict
        ``normals_key``, ``depth_key`` (stage keys), ``normals_sha256``, ``depth_sha256``
        (content digests of the normals ``(K, H, W, 3)`` and heights ``(K, H, W)``),
        ``valid_fraction``, ``contacts`` (K), ``outputs``, and with truth in the capture
        ``normal_mean_error_deg`` and ``depth_rmse_mm``.
    """
    from pipeline.reconstruct import reconstruct

    dest = None if out is None else str(Path(out) / Path(recording).stem)
    res = reconstruct(recording, calibration=calibration, illumination=illumination, solver=solver,
                      integrator=integrator, out=dest, store=store, images=images, device=device, heal=heal,
                      mask=mask, markers=markers, threads=threads, drift=drift)
    n, d = res.normals, res.depth
    result = {"normals_key": n.provenance.get("iristac_key") or "", "depth_key": d.provenance.get("iristac_key") or "",
              "normals_sha256": _sha(n.data["normals"]), "depth_sha256": _sha(d.data["height"]),
              "contacts": int(n.data["normals"].shape[0]), "valid_fraction": res.summary["valid_fraction"],
              "outputs": res.summary.get("outputs", [])}
    for k in ("normal_mean_error_deg", "depth_rmse_mm"):
        if k in res.summary:
            result[k] = res.summary[k]
    return result


def expand_recordings(paths: Sequence[str]) -> list[str]:
    """Files as given; folders become their ``*.h5`` files, sorted.

    Raises
    ------
    UserError
        A path that does not exist, or nothing to process.
    """
    out: list[str] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += [str(f) for f in sorted(p.glob("*.h5"))]
        elif p.exists():
            out.append(str(p))
        else:
            raise UserError(f"{p}: no such recording (expected a capture.h5 or a folder of them)")
    if not out:
        raise UserError(f"no recordings to process in {', '.join(map(str, paths)) or '(none given)'}")
    return out


def batch_reconstruct(recordings: Sequence[str], *, calibration: str | None = None, illumination: str | None = None,
                      solver: str = "lstsq", integrator: str = "dst", out: str | None = None,
                      store: str | None = None, images: bool = False, device: str = "cpu", workers: int = 1,
                      scheduler: str | None = None, progress: bool = False, connect_timeout: float = 10.0,
                      heal: bool = True, mask: str | None = None, markers: str | None = None,
                      threads: int | None = 1, drift: str = "auto"):
    """Reconstruct every recording with a shared calibration or illumination model.

    Parameters
    ----------
    recordings : sequence of str
        ``capture.h5`` files or folders of them (:func:`expand_recordings`).
    calibration, illumination : str, optional
        The shared light model (at most one).
    workers : int
        Local processes (1: in this process).
    scheduler : str, optional
        A Dask scheduler address (``tcp://host:8786``): the recordings are spread over its
        workers, which must see the same paths (and the store) as this machine.
    threads : int, optional
        Threads within each recording (:func:`reconstruct_recording`): frame-level parallelism
        for one process; ``workers`` adds processes, one recording each.
    solver, integrator, out, store, images, device, heal, progress, connect_timeout, mask, markers, drift
        See :func:`reconstruct_recording` and :func:`pipeline.batch.run_batch`.

    Returns
    -------
    list of pipeline.batch.BatchItem
        One per recording, in input order.
    """
    from pipeline.batch import run_batch

    if calibration is not None and illumination is not None:
        raise UserError("batch: give either --calibration or --illumination, not both")
    marker_file = markers if markers not in (None, "auto", "none") else None
    for flag, path in (("--calibration", calibration), ("--illumination", illumination), ("--mask", mask),
                       ("--markers", marker_file)):
        if path is not None and not Path(path).is_file():
            raise UserError(f"{flag} {path}: no such file")
    # Workers may run elsewhere or in another folder: hand them absolute paths.
    def absolute(p):
        return None if p is None else str(Path(p).resolve())

    recs = [str(Path(r).resolve()) for r in expand_recordings(recordings)]
    if store is None:
        from pipeline.base.store import default_store_root

        store = str(default_store_root())
    task = partial(reconstruct_recording, calibration=absolute(calibration), illumination=absolute(illumination),
                   solver=solver, integrator=integrator, out=absolute(out), store=absolute(store), images=images,
                   device=device, heal=heal, mask=absolute(mask),
                   markers=absolute(marker_file) if marker_file else markers, threads=threads, drift=drift)
    return run_batch(recs, task, workers=workers, scheduler=scheduler, progress=progress,
                     connect_timeout=connect_timeout)
