"""The lens design space: which scene dimensions vary, within which bounds, and how.

A design is a dict ``{parameter: value}``; :class:`DesignSpace` maps it to and from the unit
cube the optimizers search (linear, or logarithmic for the top radius, whose useful values
span 20 mm to a flat window) and builds the candidate :class:`sim.scene.Scene` from the base
scene (re-validated: a design that does not close into a lens raises
:class:`pipeline.errors.UserError`, which the optimizer counts as infeasible).

Parameters (:data:`PARAMETERS`):

==================  ======================================  =======
name                what                                    unit
==================  ======================================  =======
``arc_radius``      radius of the side's swept arc          mm
``centre_rho``      distance of the arc's centre from z     mm
``centre_z``        height of the arc's centre              mm
``top_radius``      apex radius of curvature of the top     mm (log scale)
``top_conic``       conic constant of the top (0: sphere)   1
``apex_z``          height of the top's apex                mm
``bottom_z``        height of the flat bottom               mm
``led_tilt_deg``    LED tilt toward the axis                deg
==================  ======================================  =======
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.base.errors import UserError
from sim.scene import Scene, scene_from_dict, scene_to_dict

__all__ = ["PARAMETERS", "LENGTHS", "DEFAULT_BOUNDS", "DesignSpace", "design_of", "apply_design"]

#: Every parameter a design may vary: name -> (section path in the scene file, unit).
PARAMETERS = {
    "arc_radius": (("lens", "side", "arc_radius"), "mm"),
    "centre_rho": (("lens", "side", "centre_rho"), "mm"),
    "centre_z": (("lens", "side", "centre_z"), "mm"),
    "top_radius": (("lens", "top", "radius"), "mm"),
    "top_conic": (("lens", "top", "conic"), ""),
    "apex_z": (("lens", "top", "apex_z"), "mm"),
    "bottom_z": (("lens", "bottom", "z"), "mm"),
    "led_tilt_deg": (("leds", "tilt_deg"), "deg"),
}

#: The parameters that are lengths (the tolerance analysis moves each by +-0.1 mm).
LENGTHS = ("arc_radius", "centre_rho", "centre_z", "apex_z", "bottom_z")

_LOG = frozenset({"top_radius"})

#: Bounds used when neither the scene's ``design.vary`` nor the caller gives any (mm, deg).
DEFAULT_BOUNDS = {
    "arc_radius": (3.0, 40.0),
    "centre_rho": (0.0, 50.0),
    "centre_z": (-10.0, 25.0),
    "top_radius": (20.0, 1e5),
    "top_conic": (-10.0, 5.0),
    "apex_z": (2.0, 40.0),
    "bottom_z": (0.3, 12.0),
    "led_tilt_deg": (-10.0, 45.0),
}


def design_of(scene: Scene) -> dict:
    """The current value of every parameter of ``scene`` (lens parameters need a swept-arc lens).

    Examples
    --------
    >>> from sim.scene import load_scene
    >>> d = design_of(load_scene("default-v1"))
    >>> d["arc_radius"], d["top_radius"], d["top_conic"], d["led_tilt_deg"]
    (13.5, 600.0, 0.0, 0.0)
    """
    ln = scene.lens
    if ln is None or not ln.is_arc:
        raise UserError(f"lens design: scene {scene.name!r} needs a lens with a swept-arc side")
    return {"arc_radius": ln.arc_radius, "centre_rho": ln.centre_rho, "centre_z": ln.centre_z,
            "top_radius": ln.top_radius, "top_conic": ln.top_conic, "apex_z": ln.apex_z, "bottom_z": ln.bottom_z,
            "led_tilt_deg": scene.leds.tilt_deg}


def apply_design(scene: Scene, design: dict, *, name: str | None = None, description: str | None = None) -> Scene:
    """``scene`` with the parameters of ``design`` set (re-validated; raises ``UserError`` if it
    does not close into a lens or puts an LED inside it)."""
    d = scene_to_dict(scene)
    if "lens" not in d:
        raise UserError(f"lens design: scene {scene.name!r} has no lens")
    for key, value in design.items():
        if key not in PARAMETERS:
            raise UserError(f"lens design: unknown parameter {key!r}; expected one of {', '.join(PARAMETERS)}")
        path, _ = PARAMETERS[key]
        node = d
        for part in path[:-1]:
            node = node[part]
        node[path[-1]] = float(value)
    if name is not None:
        d["name"] = name
    if description is not None:
        d["description"] = description
    return scene_from_dict(d, source=scene.source)


@dataclass(frozen=True)
class DesignSpace:
    """The varied parameters, their bounds and the fixed rest of the design.

    Parameters
    ----------
    base : Scene
        Everything not varied comes from it.
    bounds : dict
        ``{parameter: (low, high)}`` of the varied parameters (in search order).

    Examples
    --------
    >>> from sim.scene import load_scene
    >>> sp = DesignSpace(load_scene("default-v1"), {"apex_z": (10.0, 20.0), "top_radius": (100.0, 10000.0)})
    >>> u = sp.encode({"apex_z": 15.0, "top_radius": 1000.0})
    >>> [round(float(x), 6) for x in u]
    [0.5, 0.5]
    >>> {k: round(v, 9) for k, v in sp.decode(u).items()}
    {'apex_z': 15.0, 'top_radius': 1000.0}
    """

    base: Scene
    bounds: dict

    def __post_init__(self):
        if not self.bounds:
            raise UserError("lens design: no parameter to vary")
        for k, (lo, hi) in self.bounds.items():
            if k not in PARAMETERS:
                raise UserError(f"lens design: unknown parameter {k!r}; expected one of {', '.join(PARAMETERS)}")
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise UserError(f"lens design: bounds of {k} must be finite with low < high, got ({lo}, {hi})")
            if k in _LOG and lo <= 0:
                raise UserError(f"lens design: bounds of {k} must be positive, got ({lo}, {hi})")

    @property
    def names(self) -> list[str]:
        return list(self.bounds)

    def _to_unit(self, k, v):
        lo, hi = self.bounds[k]
        if k in _LOG:
            return (math.log(v) - math.log(lo)) / (math.log(hi) - math.log(lo))
        return (v - lo) / (hi - lo)

    def _from_unit(self, k, u):
        lo, hi = self.bounds[k]
        u = min(max(float(u), 0.0), 1.0)
        if k in _LOG:
            return float(math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))))
        return float(lo + u * (hi - lo))

    def encode(self, design: dict) -> np.ndarray:
        """Unit-cube coordinates ``(d,)`` of a design (clipped to the bounds)."""
        return np.clip(np.array([self._to_unit(k, design[k]) for k in self.names]), 0.0, 1.0)

    def decode(self, u) -> dict:
        """The design ``{parameter: value}`` at unit-cube point ``u`` (clipped into the cube)."""
        return {k: self._from_unit(k, x) for k, x in zip(self.names, np.asarray(u, dtype=float))}

    def full(self, design: dict) -> dict:
        """Every parameter: the varied ones from ``design``, the rest from the base scene."""
        return {**design_of(self.base), **design}

    def scene(self, design: dict, **kw) -> Scene:
        """The candidate scene (raises ``UserError`` for a geometry that is not a valid lens)."""
        return apply_design(self.base, design, **kw)
