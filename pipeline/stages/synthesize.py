"""Stage 1, synthesize: the sensor's per-pixel illumination model (``illumination.h5``).

Two models: ``traced`` (:func:`sim.synthesize.synthesize_record`, the ray tracer on a scene)
and ``bare_ring`` (:func:`sim.render.bare_ring_illumination`, the LED ring without a lens in
closed form). Parameters that change the result, and so enter the key (:func:`params`):
the model, the image grid (``shape``, ``mm_per_px``) and, traced, the scene's content (not
its name, path or description), rays, sampler, seed, method, float type, exposure and the
optional patterns and gains, and the tracing engine (the compiled kernel and the torch
reference draw different random and Sobol points); bare ring, the gel's ``gel_z``. The device
stays out. ``iristac run``, ``iristac demo``, ``compare-modes`` and ``iristac sim synthesize`` all
key a trace here, so the same trace is one cache entry whoever asks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from pipeline.base.errors import UserError
from pipeline.stages.base import StageSpec, config_path

__all__ = ["SPEC", "params", "compute", "run", "illumination_record", "illumination_model", "resolve", "node"]

# version 2: traced by the compiled kernel by default (sim.optics.engine), "engine" in the key.
SPEC = StageSpec("synthesize", version=2, schema="illumination",
                 # rays, sampler and seed of a traced model default to the scene's ``trace`` section.
                 defaults={"model": "traced", "scene": "default", "method": "hits", "gel_z": 35.0, "height": 60,
                           "width": 80, "mm_per_px": 0.5})


def params(section: Mapping[str, Any]) -> dict:
    """The key parameters of a synthesize section (a run config's, or :func:`run`'s options).

    Keys of ``section``
    -------------------
    model : {"traced", "bare_ring"}
        Default ``traced``.
    height, width : int
        The image grid (or ``shape`` ``(H, W)``).
    mm_per_px : float
    scene : Scene, or a shipped scene name or YAML path (traced)
        Its content enters the key (without the description).
    gel_z : float
        Optical z of the gel (bare ring; default 35).
    rays, sampler, seed : optional
        Traced: default to the scene's ``trace`` section.
    method, dtype, exposure, drive, brightness, gains, engine : optional
        Traced: as in :func:`sim.synthesize.synthesize` (``engine`` None: the default one).

    Examples
    --------
    >>> params({"model": "bare_ring", "height": 4, "width": 6, "mm_per_px": 0.5})
    {'model': 'bare_ring', 'shape': [4, 6], 'mm_per_px': 0.5, 'gel_z': 35.0}
    """
    p = dict(section)
    model, mm_per_px = p.get("model", "traced"), p["mm_per_px"]
    shape = list(p["shape"]) if "shape" in p else [p["height"], p["width"]]
    shape = [int(shape[0]), int(shape[1])]
    if model == "bare_ring":
        return {"model": "bare_ring", "shape": shape, "mm_per_px": float(mm_per_px), "gel_z": float(p.get("gel_z", 35.0))}
    if model != "traced":
        raise UserError(f"synthesize: model must be 'traced' or 'bare_ring', got {model!r}")
    from sim.scene import Scene, load_scene, scene_to_dict

    scene = p.get("scene")
    try:
        sc = scene if isinstance(scene, Scene) else load_scene(scene)
    except UserError as exc:
        raise UserError(f"synthesize: scene: {exc}") from None
    from sim.optics.engine import float_dtype, resolve_engine

    tr = sc.trace
    d = scene_to_dict(sc)
    d.pop("description", None)  # words do not change the light
    d.pop("design", None)  # nor does the lens optimizer's brief
    given = {k: p.get(k) for k in ("rays", "sampler", "seed", "dtype", "engine")}
    out: dict[str, Any] = {"model": "traced", "scene": d, "shape": shape, "mm_per_px": float(mm_per_px),
                           "rays": int(given["rays"] if given["rays"] is not None else tr.rays),
                           "sampler": given["sampler"] or tr.sampler,
                           "seed": int(tr.seed if given["seed"] is None else given["seed"]),
                           "method": p.get("method") or "hits", "dtype": float_dtype(given["dtype"] or "float32").name,
                           "exposure": float(p.get("exposure", 1.0)),
                           "engine": resolve_engine(given["engine"], tr.intersection, sc)}
    for name in ("drive", "brightness", "gains"):
        if p.get(name) is not None:
            out[name] = np.asarray(p[name], dtype=np.float64)
    return out


def run(store, scene, shape, mm_per_px: float, *, force: bool = False, heal: bool = True, **kw):
    """:func:`sim.synthesize.synthesize` through ``store``: returns ``(model, key, cached)`` (the
    :class:`~sim.illumination_model.IlluminationModel`, not the record).

    ``kw`` are :func:`sim.synthesize.synthesize`'s options (``drive``, ``brightness``,
    ``gains``, ``exposure``, ``rays``, ``sampler``, ``seed``, ``method``, ``device``,
    ``dtype``, ``engine``). ``key`` is this stage's key (:func:`params`); ``cached`` says
    whether the entry was read back instead of traced.
    """
    from sim.optics.multisource import METHODS
    from sim.scene import Scene, load_scene
    from sim.synthesize import check_inputs, model_from_record, synthesize_record

    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    full = dict(drive=None, brightness=None, gains=None, exposure=1.0, rays=None, sampler=None, seed=None,
                method="hits", device="cpu", dtype=None, engine=None)
    full.update(kw)
    if full["method"] not in METHODS:
        raise UserError(f"synthesize: method must be one of {METHODS}, got {full['method']!r}")
    check_inputs(sc, shape, mm_per_px, full["drive"], full["brightness"], full["gains"])
    shape = (int(shape[0]), int(shape[1]))
    p = params({"model": "traced", "scene": sc, "shape": shape, "mm_per_px": mm_per_px,
                **{k: full[k] for k in ("rays", "sampler", "seed", "method", "dtype", "exposure", "drive",
                                        "brightness", "gains", "engine")}})
    rec, key, cached = SPEC.get_or_compute(store, p, [], lambda: synthesize_record(sc, shape, mm_per_px, **full),
                                           force=force, heal=heal)
    return model_from_record(rec), key, cached


def illumination_record(model):
    """An :class:`~sim.illumination_model.IlluminationModel` as an ``illumination`` record.

    Parameters
    ----------
    model : IlluminationModel
        ``V (L, H, W, 3)``, ``led_positions (L, 3)``, ``mm_per_px``, ``gel_z``.

    Returns
    -------
    Record
        Schema ``illumination``: ``V``, ``led_positions`` (and ``V_depth``/``depth_heights``
        when the model has them); attributes ``mm_per_px``, ``gel_z`` and the model's scalar
        ``meta`` entries.

    Examples
    --------
    >>> from sim.render import bare_ring_illumination
    >>> rec = illumination_record(bare_ring_illumination((4, 6), 1.0))
    >>> rec.data["V"].shape, rec.meta["source"]
    ((24, 4, 6, 3), 'bare_ring')
    """
    from pipeline.base.store import Record

    data = {"V": np.asarray(model.V, dtype=np.float32), "led_positions": np.asarray(model.led_positions, np.float32)}
    if model.V_depth is not None:
        data["V_depth"] = np.asarray(model.V_depth, dtype=np.float32)
        data["depth_heights"] = np.asarray(model.depth_heights, dtype=np.float32)
    meta = {k: v for k, v in model.meta.items() if isinstance(v, (str, int, float, bool))}
    meta.update({"mm_per_px": float(model.mm_per_px), "gel_z": float(model.gel_z)})
    return Record("illumination", data, meta)


def illumination_model(rec):
    """The :class:`~sim.illumination_model.IlluminationModel` of an ``illumination`` record.

    The ray tracer's reader, :func:`sim.synthesize.model_from_record`.

    Examples
    --------
    >>> from sim.render import bare_ring_illumination
    >>> m = illumination_model(illumination_record(bare_ring_illumination((4, 6), 1.0)))
    >>> m.shape, m.num_leds
    ((4, 6), 24)
    """
    from sim.synthesize import model_from_record

    return model_from_record(rec)


def compute(p: Mapping[str, Any], device: str = "cpu"):
    """The ``illumination`` record of a resolved config section (no caching)."""
    shape = (int(p["height"]), int(p["width"]))
    if p["model"] == "bare_ring":
        from sim.render import bare_ring_illumination

        return illumination_record(bare_ring_illumination(shape, float(p["mm_per_px"]), float(p["gel_z"])))
    from sim.synthesize import synthesize_record

    return synthesize_record(p["scene"], shape, float(p["mm_per_px"]), rays=int(p["rays"]), sampler=p["sampler"],
                             seed=int(p["seed"]), method=p["method"], device=device)


def resolve(syn: dict, config: Mapping[str, Any], base: Path, source: str) -> None:
    """Fill a run config's ``synthesize`` section in place: a scene file next to the config
    becomes an absolute path; a traced model's rays, sampler and seed default to the scene's."""
    if (base / syn["scene"]).is_file():
        syn["scene"] = config_path(syn["scene"], base)  # a scene file next to the config
    if syn["model"] == "traced" and not all(k in syn for k in ("rays", "sampler", "seed")):
        from sim.scene import load_scene

        try:
            trace = load_scene(syn["scene"]).trace
        except UserError as exc:
            raise UserError(f"{source}: synthesize.scene: {exc}") from None
        syn.update({k: v for k, v in (("rays", trace.rays), ("sampler", trace.sampler), ("seed", trace.seed))
                    if k not in syn})


def node(config: Mapping[str, Any], ctx):
    """The graph node of a resolved run config's ``synthesize`` section."""
    from pipeline.stages.graph import Stage

    p = config["synthesize"]
    keys = ("model", "height", "width", "mm_per_px") + (("gel_z",) if p["model"] == "bare_ring" else
                                                         ("scene", "rays", "sampler", "seed", "method"))
    return Stage(SPEC.name, SPEC.version, params({k: p[k] for k in keys}), [], lambda inputs: compute(p, ctx.device),
                 schema=SPEC.schema)
