"""The virtual sensor's calibration for live use, keyed so that a cache hit renders nothing.

:func:`virtual_calibration` calibrates the virtual sensor for a lighting mode the way the demo
does (rendered ball presses through the calibrate stage); :func:`virtual_calibration_key` is
the store key it files the result under (``docs/live.md``, start-up).
"""

from __future__ import annotations

__all__ = ["virtual_calibration", "virtual_calibration_key"]


def _needed_models(solver: str) -> list[str]:
    """The models a virtual calibration fits for ``solver``: the one it applies, else the
    light-field models."""
    from pipeline.base.registry import SOLVERS

    needs = str(SOLVERS.get(solver).info.get("needs", ""))
    if needs.startswith("model:"):
        return [needs[6:]]
    return ["far", "near", "traced"]


def _virtual_calibration_section(model, ill_key, mode: str, solver: str, ball_radius_mm: float, presses: int,
                                 noise_dn: float, seed: int):
    """The calibrate section and key inputs of :func:`virtual_calibration`."""
    from pipeline.base.hashing import digest
    from pipeline.base.modes import load_mode
    from pipeline.stages import calibrate as calibrate_stage

    patterns = load_mode(mode)
    p = calibrate_stage.rendered({"presses": presses, "depth_mm": 0.6, "noise_dn": noise_dn, "target_dn": 200.0,
                                  "spread_mm": 0.3 * min(model.shape) * model.mm_per_px, "seed": seed, "mode": mode},
                                 ball_radius_mm=ball_radius_mm, models=_needed_models(solver))
    # The key holds what the rendering reads besides the parameters: the light field
    # (``ill_key``), the sensor's size and pitch, and the mode's patterns by content (a mode
    # file or a built-in mode that changes must not find the old calibration).
    seen = digest({"shape": list(model.shape), "mm_per_px": float(model.mm_per_px), "drive": patterns.drive,
                   "brightness": patterns.brightness})
    return p, [str(ill_key), "sensor:" + seen]


def virtual_calibration(store, model, ill_key, mode: str, solver: str, *, ball_radius_mm: float = 2.0,
                        presses: int = 8, noise_dn: float = 1.0, seed: int = 11):
    """Calibrate the virtual sensor for ``mode`` as the demo does: ball presses rendered under the
    mode's patterns, fitted through the calibrate stage (cached in ``store``). Returns the
    ``calibration`` Record.

    The models fitted are the one ``solver`` applies (``lut``, ``mlp`` ...), else the light-field
    models (far, near, traced: the light field the near-field and far-field solvers use).
    ``ill_key`` identifies ``model`` (its light field). The store keys the result by the
    rendering's parameters (:func:`pipeline.stages.calibrate.run_rendered`), so a cached
    calibration is found without rendering its presses (live start-up, docs/live.md).
    """
    from pipeline.stages import calibrate as calibrate_stage

    p, inputs = _virtual_calibration_section(model, ill_key, mode, solver, ball_radius_mm, presses, noise_dn, seed)
    rec, _, _ = calibrate_stage.run_rendered(store, p, model, inputs)
    return rec


def virtual_calibration_key(store, model, ill_key, mode: str, solver: str, *, ball_radius_mm: float = 2.0,
                            presses: int = 8, noise_dn: float = 1.0, seed: int = 11):
    """The store key :func:`virtual_calibration` files its result under (same arguments)."""
    from pipeline.stages import calibrate as calibrate_stage

    p, inputs = _virtual_calibration_section(model, ill_key, mode, solver, ball_radius_mm, presses, noise_dn, seed)
    return calibrate_stage.SPEC.key(store, calibrate_stage.params(p), inputs)
