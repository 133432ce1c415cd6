"""Stage 5, depth: integrate every contact instance's normals into a height map.

Parameters that change the result, and so enter the key: the integrator, and the pixel pitch
``mm_per_px`` the gradients are scaled by (heights scale with it). Both entry points pass
the same value: ``reconstruct`` the capture's, ``run`` the one its capture section will
record (:func:`pipeline.stages.capture.scale`). Input: the normals stage's key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.registry import INTEGRATORS
from pipeline.stages.base import StageSpec

__all__ = ["SPEC", "params", "resolve", "compute", "run", "node"]

SPEC = StageSpec("depth", version=2, schema="depth",  # 2: on the capture's mask (its bounding box)
                 defaults={"integrator": "dst"})


def params(section: Mapping[str, Any]) -> dict:
    """The key parameters of a depth section: ``integrator`` and ``mm_per_px`` (None only when a
    run config's capture file cannot be read yet: that run then fails at the capture stage).

    Examples
    --------
    >>> params({"integrator": "dst", "mm_per_px": 0.1})
    {'integrator': 'dst', 'mm_per_px': 0.1}
    """
    mm = section.get("mm_per_px")
    return {"integrator": INTEGRATORS.check(section["integrator"]), "mm_per_px": None if mm is None else float(mm)}


def resolve(section: dict, config: Mapping[str, Any], base: Path, source: str) -> None:
    """A run config's ``depth`` section needs nothing filled beyond its defaults (the pitch is
    the capture's, :func:`pipeline.stages.capture.scale`)."""


def compute(n_rec, integrator: str = "dst", mm_per_px: float | None = None, region=None, device="cpu",
            threads: int | None = 1):
    """Integrate every instance of a ``normals`` record into a ``depth`` record (no caching).

    Parameters
    ----------
    n_rec : Record
        Schema ``normals``: ``normals (K, H, W, 3)``, ``mask (K, H, W)``, optional ``filled
        (H, W)`` (filled-in marker pixels, integrated through), attribute ``mm_per_px``.
    integrator : str
        A name in :data:`pipeline.base.registry.INTEGRATORS`.
    mm_per_px : float, optional
        The pitch the stage was keyed with; it must be the normals record's.
    region : ndarray, shape (H, W), bool, optional
        The solved region (:func:`pipeline.solving.regions.capture_region`): ``sparse``
        integrates on it, the others on its bounding box (:func:`pipeline.depth.integrate`).
        It is decided by the normals stage's inputs, so it needs no key of its own.
    device : str
        ``dst`` on the whole frame with a device other than the CPU: every instance at once by
        FFT on the device (:func:`pipeline.depth.batched.dst_heights`; equal to the DST to
        float rounding, so the device stays out of the key).
    threads : int, optional
        Instances integrated at once, one per thread (:class:`pipeline.base.frame_pool.FramePool`;
        None: every core). ``dst`` on the whole frame with float32 normals and other than one
        thread: :meth:`pipeline.depth.fast.FastDST.integrate_batch` (each thread a run of
        instances in one compiled call and one transform pair; equal to the DST to float32
        rounding). The count stays out of the key.

    Returns
    -------
    Record
        Schema ``depth``: ``height (K, H, W)`` in mm and ``mask (K, H, W)``.
    """
    from pipeline.base.store import Record
    from pipeline.depth import integrate

    INTEGRATORS.check(integrator)
    pitch = float(n_rec.meta["mm_per_px"])
    if mm_per_px is not None and not np.isclose(pitch, mm_per_px, rtol=1e-9, atol=0.0):
        raise UserError(f"depth: the normals are at {pitch} mm/px but the stage was keyed with {mm_per_px} "
                        f"(the capture's pitch differs from its config section's)")
    # Filled-in marker pixels (``filled``) are no measurements but fit to integrate through:
    # taken as flat gel they would dent every contact they cross.
    filled = n_rec.data.get("filled")
    if integrator == "dst" and region is None and str(device) != "cpu":
        return _compute_on_device(n_rec, pitch, filled, device)
    if integrator == "dst" and region is None and threads != 1 and n_rec.data["normals"].dtype == np.float32:
        return _compute_fast(n_rec, pitch, filled, threads)
    usable = [n_rec.data["mask"][k] if filled is None else (n_rec.data["mask"][k] | filled)
              for k in range(n_rec.data["normals"].shape[0])]
    from pipeline.base.frame_pool import FramePool

    with FramePool(threads) as pool:
        outs = pool.map(lambda k: integrate(n_rec.data["normals"][k], pitch, usable[k], method=integrator,
                                            region=region), range(n_rec.data["normals"].shape[0]))
    data = {"height": np.stack([o.height for o in outs]), "mask": np.stack([o.mask for o in outs])}
    meta: dict[str, Any] = {"integrator": integrator, "mm_per_px": pitch}
    if integrator == "sparse":
        meta["converged"] = bool(all(o.meta["converged"] for o in outs))
    return Record("depth", data, meta)


def _compute_fast(n_rec, pitch: float, filled, threads):
    """``dst`` of every instance by :meth:`pipeline.depth.fast.FastDST.integrate_batch` on
    ``threads`` threads (a run of instances each; see :func:`compute`)."""
    from pipeline.base.frame_pool import FramePool
    from pipeline.base.store import Record
    from pipeline.depth.fast import FastDST

    n = np.asarray(n_rec.data["normals"])
    m = np.asarray(n_rec.data["mask"], bool)
    if filled is not None:
        m = m | np.asarray(filled, bool)
    with FramePool(threads) as pool:
        h, valid = FastDST(n.shape[1:3], pitch).integrate_batch(n, m, pool)
    return Record("depth", {"height": h, "mask": valid}, {"integrator": "dst", "mm_per_px": pitch, "method": "fast"})


def _compute_on_device(n_rec, pitch: float, filled, device):
    import torch

    from pipeline.base.store import Record
    from pipeline.depth.batched import dst_divergence_torch, dst_heights

    n = torch.as_tensor(np.asarray(n_rec.data["normals"], np.float32), device=device)
    m = np.asarray(n_rec.data["mask"], bool)
    if filled is not None:
        m = m | np.asarray(filled, bool)
    f, valid = dst_divergence_torch(n, torch.as_tensor(m, device=device), pitch)
    h = dst_heights(f)
    return Record("depth", {"height": h.cpu().numpy().astype(np.float32), "mask": valid.cpu().numpy()},
                  {"integrator": "dst", "mm_per_px": pitch, "device": str(device)})


def run(store, n_rec, n_key, *, integrator: str = "dst", force: bool = False, heal: bool = True, region=None,
        device="cpu", threads: int | None = 1):
    """``(record, key, cached)`` of the depth of ``n_rec`` (identified by ``n_key``) through
    ``store``, integrated on ``region`` (see :func:`compute`)."""
    mm = float(n_rec.meta["mm_per_px"])
    return SPEC.get_or_compute(store, params({"integrator": integrator, "mm_per_px": mm}), [n_key],
                               lambda: compute(n_rec, integrator, mm, region, device, threads), force=force,
                               heal=heal)


def node(config: Mapping[str, Any], ctx):
    """The graph node of a resolved run config's ``depth`` section."""
    from pipeline.stages import capture
    from pipeline.stages.graph import Stage

    p = config["depth"]
    ctx.need("depth", "normals")
    mm = capture.scale(config)
    return Stage(SPEC.name, SPEC.version, params({"integrator": p["integrator"], "mm_per_px": mm}), ["normals"],
                 lambda inputs: compute(inputs["normals"], p["integrator"], mm), schema=SPEC.schema)
