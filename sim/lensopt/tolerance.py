"""Tolerance analysis: how much flux and uniformity a design loses when a dimension is off.

Each dimension of the design is moved both ways in turn (:func:`perturbations`: lengths by
``delta`` mm, 0.1 by default; the top's radius and conic constant so that the top's surface
moves by ``delta`` mm at the lens's rim; the LED tilt by ``tilt_delta`` degrees) and
the design is traced again with the same rays as the nominal one (common random numbers, so
that a 0.1 mm change is not lost in Monte Carlo noise). A perturbation that no longer makes a
lens (or touches an LED) is reported as such.
"""

from __future__ import annotations

import math

from pipeline.base.errors import UserError
from sim.lensopt.objectives import Evaluator
from sim.lensopt.space import LENGTHS, apply_design, design_of
from sim.scene import Scene

__all__ = ["tolerance_table", "perturbations"]


def _sag(R, k, rho):
    e = 1.0 + k
    arg = 1.0 - e * rho * rho / (R * R)
    return rho * rho / (R * (1.0 + math.sqrt(max(arg, 0.0))))


def perturbations(scene: Scene, names, delta: float = 0.1, tilt_delta: float = 0.5) -> dict:
    """``{parameter: (value_minus, value_plus)}``: each parameter moved so that its surface moves
    by ``delta`` mm (``None`` where no such value exists, e.g. a flat top cannot curve down).

    Lengths move by ``delta``; the top's curvature ``1 / R`` by the change that moves the top's
    sag at the rim by ``delta`` (a flat top gets a ``delta`` mm dome, and the other way would be
    concave); the conic constant likewise; the LED tilt by ``tilt_delta`` degrees.

    Examples
    --------
    >>> from sim.scene import load_scene
    >>> p = perturbations(load_scene("default-v1"), ["apex_z", "led_tilt_deg", "top_radius"])
    >>> [round(v, 3) for v in p["apex_z"]], p["led_tilt_deg"], [round(v) for v in p["top_radius"]]
    ([15.9, 16.1], (-0.5, 0.5), [647, 560])
    """
    ln = scene.lens
    cur = design_of(scene)
    out = {}
    for k in names:
        v = cur[k]
        if k in LENGTHS:
            out[k] = (v - delta, v + delta)
        elif k == "led_tilt_deg":
            out[k] = (v - tilt_delta, v + tilt_delta)
        elif k == "top_radius":
            # Curvature c = 1/R; the sag at the rim grows with c: find c -+ dc moving it by -+delta.
            rho = ln.rim_rho
            f = lambda c: _sag(1.0 / c, ln.top_conic, rho) if c > 0 else 0.0  # noqa: E731
            c0 = 1.0 / ln.top_radius
            vals = []
            for target in (f(c0) - delta, f(c0) + delta):
                if target <= 0:
                    vals.append(None)  # flatter than flat: a concave top
                    continue
                lo, hi = 0.0, max(c0, 1e-12)
                while f(hi) < target and hi < 1.0 / rho:
                    hi *= 2.0
                for _ in range(100):
                    mid = 0.5 * (lo + hi)
                    lo, hi = (mid, hi) if f(mid) < target else (lo, mid)
                c = 0.5 * (lo + hi)
                vals.append(1.0 / c if c > 0 and abs(f(c) - target) < 1e-6 else None)
            out[k] = (vals[0], vals[1])
        elif k == "top_conic":
            rho, R = ln.rim_rho, ln.top_radius
            h = 1e-4
            slope = (_sag(R, v + h, rho) - _sag(R, v - h, rho)) / (2 * h)
            step = delta / abs(slope) if slope != 0 else math.inf
            out[k] = (v - step, v + step) if math.isfinite(step) else (None, None)
        else:
            raise UserError(f"tolerance: unknown parameter {k!r}")
    return out


def tolerance_table(scene: Scene, evaluator: Evaluator, names=None, delta: float = 0.1,
                    tilt_delta: float = 0.5) -> dict:
    """Flux and CV of ``scene`` with each parameter moved by -step and +step.

    Returns ``{"delta_mm", "rays", "nominal": {fraction_on_screen, uniformity_cv}, "rows": [{parameter,
    value, minus_value, plus_value, minus: {...} | None, plus: {...} | None, d_flux_max, d_cv_max,
    note}], "worst_d_flux",
    "worst_d_cv"}``, the ``d_*`` being the largest absolute change from nominal (flux in
    fractions of the emitted power).
    """
    nominal = design_of(scene)
    names = list(names) if names is not None else list(nominal)
    base = evaluator(scene)
    moves = perturbations(scene, names, delta, tilt_delta)
    rows = []
    for k in names:
        row = {"parameter": k, "value": nominal[k], "minus_value": moves[k][0], "plus_value": moves[k][1],
               "minus": None, "plus": None, "d_flux_max": None, "d_cv_max": None, "note": ""}
        df, dc = [], []
        for value, tag in zip(moves[k], ("minus", "plus")):
            if value is None:
                row["note"] += f"{tag}: no such design (the surface cannot move that way); "
                continue
            try:
                m = evaluator(apply_design(scene, {k: value}))
            except (UserError, ValueError) as exc:
                row["note"] += f"{tag}: not a valid lens ({exc}); "
                continue
            row[tag] = {"fraction_on_screen": m.fraction_on_screen, "uniformity_cv": m.uniformity_cv}
            df.append(abs(m.fraction_on_screen - base.fraction_on_screen))
            dc.append(abs(m.uniformity_cv - base.uniformity_cv))
        row["d_flux_max"] = max(df) if df else None
        row["d_cv_max"] = max(dc) if dc else None
        rows.append(row)
    flux = [r["d_flux_max"] for r in rows if r["d_flux_max"] is not None]
    cvs = [r["d_cv_max"] for r in rows if r["d_cv_max"] is not None]
    return {"delta_mm": delta, "rays": evaluator.rays,
            "nominal": {"fraction_on_screen": base.fraction_on_screen, "uniformity_cv": base.uniformity_cv},
            "rows": rows, "worst_d_flux": max(flux) if flux else None, "worst_d_cv": max(cvs) if cvs else None}
