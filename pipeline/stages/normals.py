"""Stage 4, normals: per-pixel normals, albedo, residual, condition and mask of every contact instance.

Parameters that change the result, and so enter the key: the solver
(:data:`pipeline.base.registry.SOLVERS`), ``ratio``, ``max_condition``, the float type,
where the lights come from (``calibration``, ``illumination`` or the ``capture`` itself) and
``drift``, the illumination drift removed before the solve (``auto``: a per-channel gain and
offset against the no-contact reference where the solver keys on it, :mod:`pipeline.normals.drift`;
what ``auto`` resolves to follows from the solver and the inputs, so the setting itself is keyed).
Inputs: the capture's identity and the light file's
(:func:`pipeline.base.identity.record_key`). The device, the thread count and ``compile`` do
not change the result and stay out of the key.

Where the lights come from, where a capture is solved and which markers are filled in is
decided below this stage, where ``reconstruct``, ``batch`` and ``live`` decide it too
(:mod:`pipeline.solving`): the lights' file enters the key by its identity, a user's region
(``--mask``) and the marker mask filled in by their digests.

The solve itself is the one path every entry point takes,
:class:`pipeline.normals.solve.FrameSolver` (frames prepared by
:class:`pipeline.normals.prepare.FramePrep`); this module reads the capture and writes the record.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from pipeline.base.registry import SOLVERS
from pipeline.normals.drift import check_drift
from pipeline.normals.lights import LightSource
from pipeline.solving.light_files import capture_lights
from pipeline.solving.regions import capture_region, reference_frames
from pipeline.stages.base import StageSpec

__all__ = ["SPEC", "params", "key_params", "resolve", "compute", "run", "node"]

# 2: only the capture's (or user's) mask is solved; 3: the lut solver applies the calibrated model
# (per-bin position correction, tilt gain), markers are filled in, confidence and filled are written;
# 4: illumination drift against the reference removed first (``drift``, default ``auto``).
# 5: what is written is a choice (``save``, ``precision``: :mod:`pipeline.frame_pipeline.outputs`).
# 6: the networks' (``conv``, ``conv-fast``) confidence is the share of their input window inside the frame.
SPEC = StageSpec("normals", version=6, schema="normals",
                 defaults={"solver": "lstsq", "ratio": False, "max_condition": 1e3, "dtype": "float32",
                           "drift": "auto", "save": ["confidence"], "precision": "single"})


def params(section: Mapping[str, Any]) -> dict:
    """The key parameters of a normals section: ``solver``, ``ratio``, ``max_condition``,
    ``dtype``, ``drift``, what is written (``save``, ``precision``: :meth:`pipeline.frame_pipeline.outputs.OutputSpec.key_params`;
    defaults :data:`SPEC`'s) and ``lights`` (``calibration``, ``illumination`` or
    ``capture``); ``mask``, a user's region (the capture's own is part of the capture's
    identity), enters as its digest, and so does the marker mask filled in (``markers``,
    :func:`pipeline.solving.regions.marker_mask`).

    Examples
    --------
    >>> params({"solver": "nearfield", "lights": "illumination"})["solver"]
    'nearfield'
    """
    s = {**SPEC.defaults, **section}
    p = {"solver": SOLVERS.check(s["solver"]), "ratio": bool(s["ratio"]), "max_condition": float(s["max_condition"]),
         "dtype": str(s["dtype"]), "lights": str(s["lights"]), "drift": check_drift(s["drift"]),
         "save": sorted(str(x) for x in s["save"] if x != "confidence" or _rates_itself(s["solver"])),
         "precision": str(s["precision"])}
    for name in ("mask", "markers"):
        if s.get(name) is not None:
            from pipeline.base.hashing import digest

            p[name] = digest(np.asarray(s[name], bool))
    return p


def _rates_itself(solver: str) -> bool:
    """Whether ``solver`` gives a confidence (the calibration's models do): for the others asking
    for one changes nothing, so it stays out of the key."""
    return str(SOLVERS.get(solver).info.get("needs", "")).startswith("model:")


def resolve(section: dict, config: Mapping[str, Any], base: Path, source: str) -> None:
    """Fill a run config's ``normals`` section in place: the lights default to the calibration
    when the config calibrates, else to the synthesized illumination."""
    section.setdefault("lights", "calibration" if "calibrate" in config else "illumination")


def _stack(results, name: str) -> np.ndarray:
    return np.stack([getattr(r, name) for r in results])


def compute(cap, lights: LightSource, *, solver: str = "lstsq", ratio: bool = False, max_condition: float = 1e3,
            device="cpu", dtype="float32", threads: int | None = 1, compile: bool = False, mask=None, markers=None,
            batched: bool | None = None, drift: str = "auto", outputs=None):
    """The ``normals`` :class:`~pipeline.base.store.Record` of a capture (no caching).

    Parameters
    ----------
    cap : Record
        Schema ``capture``: ``frames (K, P, H, W, C)``, optional ``reference (P, H, W, C)``,
        ``dark (H, W, C)`` and ``mask (H, W)``; attributes ``mm_per_px`` and ``bit_depth``.
    lights : LightSource
        From :func:`pipeline.solving.light_files.load_lights`.
    solver, ratio, max_condition, device, dtype, compile
        As in :func:`pipeline.workflows.reconstruct.reconstruct`.
    mask : path or ndarray, shape (H, W), optional
        The pixels to solve, replacing the capture's ``mask`` (:func:`pipeline.solving.regions.capture_region`). Only
        they are read out of the frames and solved; the others are invalid in the result.
    markers : ndarray, shape (H, W), bool, optional
        Printed gel markers (:func:`pipeline.solving.regions.marker_mask`): filled in before the solve (the calibration
        models fill them in themselves, as ``eval calibration`` does), False in ``mask``, True
        in ``filled``.
    threads : int, optional
        Torch threads of the eager solvers (None: torch's setting). Other than 1, on the CPU:
        solvers with a batch fast path (``nearfield``, ``lstsq``: registry fact ``batch``) on
        integer frames (no ratio, no markers, float32) run it instead (:meth:`pipeline.normals.fast.NearFieldFast.solve_batch`, every
        instance at once on that many threads, None: every core); equal to the eager solvers
        to 2e-5 deg, so the count stays out of the key like the device.
    batched : bool, optional
        ``nearfield`` on the whole frame: solve all K instances as one batch on ``device``
        (:class:`pipeline.normals.batched.NearFieldBatched`, no host round trip inside the
        batch). None: when ``device`` is not the CPU. Equal to the per-instance solver to float
        rounding, so it stays out of the key like the device.
    drift : str
        The illumination drift removed before the solve (:meth:`pipeline.normals.prepare.FramePrep.use_drift`):
        ``auto`` (default: :data:`pipeline.normals.drift.AUTO_DRIFT` where the solver keys on the
        no-contact reference, which the calibration models and ``ratio`` do, and one exists:
        the capture's, else the model's), ``none``, or a model of
        :data:`pipeline.normals.drift.DRIFT_MODELS`. The batch and GPU paths take no drift: with
        one asked for by name the eager path runs.
    outputs : OutputSpec, optional
        What is written (:class:`pipeline.frame_pipeline.outputs.OutputSpec`; default its defaults).

    Returns
    -------
    Record
        Schema ``normals``: ``normals (K, H, W, 3)``, ``albedo``, ``residual``, ``condition``,
        ``mask``, ``count``; ``confidence (K, H, W)`` from the calibration models; ``filled
        (H, W)`` with markers.
    """
    from pipeline.normals.solve import FrameSolver

    raw, region, reference = cap.data["frames"], capture_region(cap, mask), reference_frames(cap)
    drift = check_drift(drift)
    plain = drift == "none" or (drift == "auto" and not SOLVERS.get(solver).info.get("keys_on_reference"))
    if batched is None:
        batched = str(device) != "cpu"
    if (batched and solver == "nearfield" and not ratio and region is None and markers is None
            and lights.field is not None and str(dtype) == "float32" and plain):
        return _select(_compute_batched(cap, lights, max_condition=max_condition, device=device), outputs)
    if (threads != 1 and str(device) == "cpu" and str(dtype) == "float32" and not ratio and markers is None
            and plain):
        res = _solve_fast_batch(cap, lights, solver=solver, max_condition=max_condition, region=region,
                                threads=threads)
        if res is not None:
            return _select(_record(res, cap, lights, solver=solver, ratio=ratio, max_condition=max_condition,
                                   region=region, markers=None), outputs)
    from pipeline.normals.drift import STREAM_SAMPLES

    prep = FrameSolver.prep_for(solver, raw.shape[2:4], raw_dtype=raw.dtype, bit_depth=cap.meta.get("bit_depth"),
                                dark=cap.data.get("dark"), markers=markers, region=region,
                                name=str(cap.path or "capture"), drift=drift, drift_samples=STREAM_SAMPLES)
    res = FrameSolver(solver, lights, prep, reference=reference, ratio=ratio, max_condition=max_condition,
                      device=device, dtype=dtype, compile=compile).solve_stack(raw, threads)
    return _select(_record(res, cap, lights, solver=solver, ratio=ratio, max_condition=max_condition, region=region,
                           markers=prep.markers), outputs)


def _select(rec, outputs):
    """``rec`` with only the datasets ``outputs`` chooses, in its precision."""
    from pipeline.frame_pipeline.outputs import NORMAL_EXTRAS, OutputSpec

    spec = outputs or OutputSpec()
    d = rec.data
    for name in NORMAL_EXTRAS:
        if name not in spec.normal_extras:
            d.pop(name, None)
    if not spec.confidence:
        d.pop("confidence", None)
    d["normals"] = np.asarray(d["normals"]).astype(spec.normals_dtype, copy=False)
    if "confidence" in d:
        d["confidence"] = np.asarray(d["confidence"]).astype(spec.normals_dtype, copy=False)
    return rec


def _record(res: list, cap, lights: LightSource, *, solver: str, ratio: bool, max_condition: float, region,
            markers):
    """The ``normals`` record of the per-instance results of :func:`compute`."""
    from pipeline.base.store import Record

    data = {name: _stack(res, name) for name in ("normals", "albedo", "residual", "condition", "mask", "count")}
    if all(r.confidence is not None for r in res) and res:
        data["confidence"] = _stack(res, "confidence").astype(np.float32)
    if markers is not None:
        # Marker pixels hold normals from filled-in observations: not measurements (False in
        # mask) but fit to integrate through (docs: NormalMaps.filled).
        data["filled"] = markers & (region if region is not None else True)
    meta = {"solver": solver, "mm_per_px": float(cap.meta["mm_per_px"]), "ratio": bool(ratio),
            "max_condition": float(max_condition), "lights": lights.source,
            "valid_fraction": float(data["mask"].mean())}
    if region is not None:
        meta["region_pixels"] = int(region.sum())
    if markers is not None:
        meta["markers"] = int(markers.sum())
    meta.update(_drift_meta(res))
    meta.update({k: v for k, v in res[0].meta.items() if k not in meta and isinstance(v, (str, int, float))})
    return Record("normals", data, meta)


def _drift_meta(res: list) -> dict:
    """``drift`` (the model removed, ``none`` if none) and, when one was, the median over the
    instances of the drift before and after removal (RMS DN of the fitted pixels)."""
    if not res or any("drift" not in r.meta for r in res):
        return {"drift": "none"}
    return {"drift": str(res[0].meta["drift"]),
            "drift_before_dn": float(np.median([r.meta["drift_before_dn"] for r in res])),
            "drift_residual_dn": float(np.median([r.meta["drift_residual_dn"] for r in res]))}


def _solve_fast_batch(cap, lights: LightSource, *, solver: str, max_condition: float, region, threads):
    """Every instance of an integer capture through the solver's batch fast path (registry fact
    ``batch``: :meth:`pipeline.normals.fast.NearFieldFast.solve_batch`) on ``threads`` threads,
    as per-instance results; None when the solver has none or the frames are not integers."""
    from pipeline.base.frame_pool import FramePool
    from pipeline.solving.frame_solvers import frame_solver

    raw = np.asarray(cap.data["frames"])
    if raw.dtype.kind not in "ui" or not SOLVERS.get(solver).info.get("batch"):
        return None
    K, P, H, W, C = raw.shape
    fs = frame_solver(solver, lights, shape=(H, W), channels=C, dark=cap.data.get("dark"), max_condition=max_condition,
                      region=region)
    with FramePool(threads) as pool:
        planes = fs.solve_batch(raw, pool)
    return [planes.result(k) for k in range(K)]


def _compute_batched(cap, lights: LightSource, *, max_condition: float, device):
    """The ``nearfield`` record of every instance at once on ``device`` (see :func:`compute`)."""
    from pipeline.base.store import Record
    from pipeline.normals.batched import NearFieldBatched

    mm_per_px = float(cap.meta["mm_per_px"])
    raw = cap.data["frames"]
    K, P, H, W, C = raw.shape
    nb = NearFieldBatched(lights.field, flat_field=lights.flat_field, max_condition=max_condition, device=device)
    out = {k: v.cpu().numpy() for k, v in nb.solve(raw, dark=cap.data.get("dark")).items()}
    cond = nb.condition.cpu().numpy().reshape(H, W)
    data = {"normals": out["normals"], "albedo": out["albedo"], "residual": out["residual"],
            "condition": np.broadcast_to(cond, (K, H, W)).copy(), "mask": out["mask"],
            "count": np.full((K, H, W), P * C, np.int32)}
    meta = {"solver": "nearfield", "mm_per_px": mm_per_px, "ratio": False, "max_condition": float(max_condition),
            "lights": lights.source, "valid_fraction": float(data["mask"].mean()), "method": "batched",
            "device": str(device)}
    return Record("normals", data, meta)


def key_params(lights: LightSource, *, solver: str = "lstsq", ratio: bool = False, max_condition: float = 1e3,
               dtype="float32", mask=None, markers=None, drift: str = "auto", outputs=None,
               colour_gain=None) -> dict:
    """The key parameters of the normals of a capture (:func:`params` of the section these
    arguments make): what :func:`run` and the streamed reconstruction (:mod:`pipeline.streaming`) key on.
    ``colour_gain``: the per-channel gain the frames were brought to the light model's colours by
    (:func:`pipeline.streaming.plan.colour_gain_for`), keyed only when given."""
    from pipeline.frame_pipeline.outputs import OutputSpec

    p = params({"solver": solver, "ratio": ratio, "max_condition": max_condition, "dtype": dtype,
                "lights": lights.source.split(":")[0], "mask": mask, "markers": markers, "drift": drift,
                **(outputs or OutputSpec()).key_params()})
    if colour_gain is not None:
        p["colour_gain"] = [float(g) for g in colour_gain]  # rounded by colour_gain_for
    return p


def run(store, cap, cap_key, lights: LightSource, *, solver: str = "lstsq", ratio: bool = False,
        max_condition: float = 1e3, device="cpu", dtype="float32", threads: int | None = 1, compile: bool = False,
        force: bool = False, heal: bool = True, mask=None, markers=None, drift: str = "auto", outputs=None):
    """``(record, key, cached)`` of the normals of ``cap`` (identified by ``cap_key``) through
    ``store``; ``mask``: a user's region (an array, see :func:`pipeline.solving.regions.capture_region`) instead of the
    capture's; ``markers``: the marker mask to fill in (:func:`pipeline.solving.regions.marker_mask`); ``drift``,
    ``outputs``: as :func:`compute`."""
    p = key_params(lights, solver=solver, ratio=ratio, max_condition=max_condition, dtype=dtype, mask=mask,
                   markers=markers, drift=drift, outputs=outputs)
    return SPEC.get_or_compute(
        store, p, [cap_key, lights.key],
        lambda: compute(cap, lights, solver=solver, ratio=ratio, max_condition=max_condition, device=device,
                        dtype=dtype, threads=threads, compile=compile, mask=mask, markers=markers, drift=drift,
                        outputs=outputs),
        force=force, heal=heal)


def node(config: Mapping[str, Any], ctx):
    """The graph node of a resolved run config's ``normals`` section (reads ``capture`` and the
    stage its ``lights`` name: ``calibrate`` or ``synthesize``)."""
    from pipeline.stages.graph import Stage

    p = config["normals"]
    ctx.need("normals", "capture")
    light_stage = "calibrate" if p["lights"] == "calibration" else "synthesize"
    ctx.need("normals", light_stage, f"with lights: {p['lights']}")

    def compute_node(inputs):
        cal = inputs.get("calibrate") if p["lights"] == "calibration" else None
        ill = inputs.get("synthesize") if p["lights"] == "illumination" else None
        lights = capture_lights(inputs["capture"], cal, ill)
        return compute(inputs["capture"], lights, solver=p["solver"], ratio=bool(p["ratio"]),
                       max_condition=float(p["max_condition"]), device=ctx.device, dtype=p["dtype"],
                       drift=p.get("drift", "auto"))

    return Stage(SPEC.name, SPEC.version, params({k: p[k] for k in ("solver", "ratio", "max_condition", "dtype",
                                                                     "lights", "drift") if k in p}),
                 ["capture", light_stage], compute_node, schema=SPEC.schema)
