"""Stage 2, calibrate: light models fitted to a sphere-indentation capture (``calibration.h5``).

:func:`calibration.calibrate.calibrate` on a sphere capture: a file (its content hash is
the stage's input), or one rendered from the synthesized illumination (the synthesize
stage's key is the input, the press layout the ``render`` parameters). Parameters that
change the result, and so enter the key (:func:`params`): the ball radius, the pixel pitch
(None: the capture's), the model or models fitted, the cross-validation folds, the source
and, rendered, its settings. A traced model also reads the illumination (its key is an
input). ``iristac run`` calibrates through :func:`node`, the demo and ``compare-modes``
through :func:`run`.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any, Mapping, Sequence

from pipeline.base.errors import UserError
from pipeline.base.identity import file_input_key, record_key
from pipeline.stages.base import StageSpec, config_path

__all__ = ["SPEC", "RENDER_DEFAULTS", "params", "compute", "run", "rendered", "run_rendered", "node", "resolve"]

# Version 2: every model's tilt gain and clip, the LUT's per-bin position correction, the MLP's
# 400 steps at 2e-2: a calibration cached by version 1 holds other models.
# Version 3: the detector scaled from the ball, per-press drift removed, the tilt gain from the
# out-of-fold ball fit, the quality gate: other circles, other models.
# Version 4: the near-field model divides by the reference's flat field, light-field models leave
# dark reference pixels out, the ball fit skips caps that are not round, every model carries its
# own verdict and the best model is a usable one: other models, other choice.
# Version 5: the contacts re-found from their shading, the default network's window sized from the
# ball and the networks without the ball's tilt gain: other circles, other networks.
SPEC = StageSpec("calibrate", version=5, schema="calibration",
                 defaults={"ball_radius_mm": 4.0, "model": "far", "folds": 5})

#: Defaults of a run config's ``calibrate.render`` (the rendered sphere capture).
RENDER_DEFAULTS = {"presses": 8, "depth_mm": 0.6, "spread_mm": 4.0, "noise_dn": 1.0, "target_dn": 200.0, "seed": 0}


def params(p: Mapping[str, Any]) -> dict:
    """The key parameters of a (default-filled) calibrate section.

    Examples
    --------
    >>> params({"capture": "s.h5", "ball_radius_mm": 2.0, "model": ["far", "lut"], "folds": 5})
    {'ball_radius_mm': 2.0, 'mm_per_px': None, 'model': ['far', 'lut'], 'folds': 5, 'source': 'file'}
    """
    model = p.get("model")
    out = {"ball_radius_mm": p.get("ball_radius_mm"), "mm_per_px": p.get("mm_per_px"),
           "model": list(model) if isinstance(model, (list, tuple)) else model, "folds": p.get("folds")}
    out["source"] = "render" if "render" in p else "file"
    if "render" in p:
        out["render"] = dict(p["render"])
    return out


def compute(p: Mapping[str, Any], illumination=None, *, device: str = "cpu"):
    """The ``calibration`` record of a (default-filled) calibrate section (no caching).

    ``illumination`` is the :class:`~sim.illumination_model.IlluminationModel` a rendered
    sphere capture is rendered with, and the traced model fits.
    """
    from calibration.calibrate import calibrate
    from pipeline.base.store import read_record

    with tempfile.TemporaryDirectory(prefix="iristac-calibrate-") as tmp:
        if "render" in p:
            from pipeline.base.capture import write_capture
            from pipeline.stages.capture import render
            from sim.contacts import contact_surfaces

            r = p["render"]
            model = illumination
            presses = contact_surfaces("sphere", model.shape, model.mm_per_px, r["presses"],
                                       size_mm=p["ball_radius_mm"], depth_mm=r["depth_mm"], spread_mm=r["spread_mm"],
                                       seed=r["seed"])
            src = write_capture(Path(tmp) / "sphere_capture.h5",
                                render(model, r["mode"], presses, r["noise_dn"], r["target_dn"], r["seed"], device))
        else:
            src = p["capture"]
        models = p["model"]
        traced = models == "traced" or (not isinstance(models, str) and "traced" in models)
        gate = None
        if "render" in p:
            from calibration.gate import MIN_ACCEPTED, GateSettings

            # A rendered capture's press count is the config's choice (its CV and ball fit still
            # gate it); the minimum of calibration.gate was measured on real frames.
            gate = GateSettings(min_accepted=min(MIN_ACCEPTED, int(p["render"]["presses"])))
        try:
            res = calibrate(src, float(p["ball_radius_mm"]), p.get("mm_per_px"), models, folds=int(p["folds"]),
                            illumination=illumination if traced else None, gate=gate)
        except UserError as exc:
            if "render" not in p:
                raise
            # The rendered file is temporary: name the config fields that made it instead.
            msg = str(exc).replace(str(src), "the sphere capture rendered from calibrate.render")
            raise UserError(f"{msg} (check calibrate.render: presses, depth_mm, spread_mm, and "
                            f"calibrate.ball_radius_mm)") from None
        return read_record(res.save(Path(tmp) / "calibration.h5"), schema="calibration")


def run(store, capture, *, ball_radius_mm: float, models: str | Sequence[str], folds: int = 5,
        mm_per_px: float | None = None, illumination=None, illumination_key=None, force: bool = False,
        heal: bool = True):
    """``(record, key, cached)``: calibrate the sphere ``capture`` through ``store``.

    ``capture`` is a ``capture.h5`` (identified by its content) or a ``capture`` Record
    (identified by :func:`pipeline.base.identity.record_key`: a rendered capture in memory by
    its data, so a rerun that renders the same presses finds this calibration).
    ``illumination`` (an IlluminationModel) and its identity ``illumination_key`` are needed
    for the ``traced`` model.
    """
    from pipeline.base.capture import capture_from_record
    from pipeline.base.store import Record

    if isinstance(capture, Record):
        source, inputs = capture_from_record(capture), [record_key(capture)]
    else:
        source, inputs = str(capture), [file_input_key(capture)]
    p = {"capture": source, "ball_radius_mm": float(ball_radius_mm), "model": models, "folds": int(folds),
         "mm_per_px": mm_per_px}
    traced = models == "traced" or (not isinstance(models, str) and "traced" in models)
    if traced:
        if illumination is None or illumination_key is None:
            raise UserError("calibrate: the traced model needs the illumination model and its key")
        inputs.append(illumination_key)
    return SPEC.get_or_compute(store, params(p), inputs, lambda: compute(p, illumination), force=force, heal=heal)


def rendered(render: Mapping[str, Any], *, ball_radius_mm: float, models: str | Sequence[str],
             folds: int = 5) -> dict:
    """The calibrate section of a sphere capture rendered from an illumination model, as a run
    config's ``calibrate.render`` (``render``: :data:`RENDER_DEFAULTS` keys, defaults filled,
    and ``mode``). Its :func:`params` are its key: :func:`run_rendered` finds a cached result
    without rendering.

    Examples
    --------
    >>> p = rendered({"mode": "trichromatic", "seed": 11}, ball_radius_mm=2.0, models=["lut"])
    >>> params(p)["render"]["seed"], params(p)["source"], params(p)["mm_per_px"]
    (11, 'render', None)
    """
    return {"render": {**RENDER_DEFAULTS, **render}, "ball_radius_mm": float(ball_radius_mm), "model": models,
            "folds": int(folds), "mm_per_px": None}


def run_rendered(store, p: Mapping[str, Any], illumination, inputs: Sequence[str], *, force: bool = False,
                 heal: bool = True):
    """``(record, key, cached)``: calibrate the rendered section ``p`` (:func:`rendered`)
    through ``store``, keyed by its parameters and ``inputs`` (the identity of
    ``illumination``, the IlluminationModel it is rendered with, and of anything else the
    rendering reads), like ``iristac run``'s ``calibrate.render``: a hit renders nothing.
    """
    return SPEC.get_or_compute(store, params(p), list(inputs), lambda: compute(p, illumination), force=force,
                               heal=heal)


def resolve(cal: dict, cfg: Mapping[str, Any], base: Path, source: str) -> None:
    """Check a run config's ``calibrate`` section, fill its ``render`` defaults (the lighting
    mode defaults to the capture's) and make its paths absolute, in place."""
    from pipeline.stages import capture

    if ("capture" in cal) == ("render" in cal):
        raise UserError(f"{source}: calibrate: give exactly one of 'capture' (a sphere capture.h5) and "
                        f"'render' (render one from the synthesized illumination)")
    if "capture" in cal:
        cal["capture"] = config_path(cal["capture"], base)
    else:
        cal["render"] = {**RENDER_DEFAULTS, "mode": capture.mode_of(cfg, base), **cal["render"]}


def node(config: Mapping[str, Any], ctx):
    """The graph node of a resolved run config's ``calibrate`` section."""
    from pipeline.stages.graph import Stage
    from pipeline.stages.synthesize import illumination_model

    p = config["calibrate"]
    if "render" in p:
        ctx.need("calibrate", "synthesize", "with 'render'")
        deps, extra = ["synthesize"], []
    else:
        try:
            deps, extra = [], [file_input_key(p["capture"])]
        except UserError as exc:
            raise UserError(f"config calibrate.capture: {exc}") from None

    def compute_node(inputs):
        model = illumination_model(inputs["synthesize"]) if "synthesize" in inputs else None
        return compute(p, model, device=ctx.device)

    return Stage(SPEC.name, SPEC.version, params(p), deps, compute_node, extra, schema=SPEC.schema)
