"""A lens design brief: what to optimise, under which limits, over which parameters, how hard.

A scene file may carry its own brief in a ``design`` section (schema
``data_schemas/configs/scene.json``), e.g. the ``paper`` scene's "most flux on screen with
a 24-LED CV of at most 0.25"; :meth:`DesignBrief.from_scene` reads it and the caller's
overrides (the command line's options) win over it, and defaults over neither.

Metric constraints are numbers or ``"bare"``: the same figure of the scene traced without
its lens (with the same rays), bettered by 1 % (:func:`sim.lensopt.objectives.bare_limit`),
so ``{"min_flux": "bare", "max_cv": "bare"}`` asks for a lens that beats the bare LEDs in
flux and in uniformity at once. ``reference`` sets parameters of that bare comparison (e.g.
``{"led_tilt_deg": 0}``: LEDs facing the gel, for a scene whose tilt is itself a design choice).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from pipeline.base.errors import UserError
from sim.lensopt.constraints import Manufacturing
from sim.lensopt.objectives import CONSTRAINTS, OBJECTIVES
from sim.lensopt.space import DEFAULT_BOUNDS, PARAMETERS

__all__ = ["DesignBrief", "DEFAULT_VARY"]

#: Parameters varied when neither the scene nor the caller says: the paper's lens family
#: (swept-arc side, spherical top, flat bottom), no new geometry and the LEDs as they are.
DEFAULT_VARY = ("arc_radius", "centre_rho", "centre_z", "top_radius", "apex_z", "bottom_z")


@dataclass(frozen=True)
class DesignBrief:
    """Every setting of one lens optimisation (see :func:`sim.lens_design.optimize_lens`)."""

    objective: str = "flux"
    modes: tuple = ()
    constraints: dict = field(default_factory=dict)
    manufacturing: Manufacturing = Manufacturing()
    vary: dict = field(default_factory=lambda: {k: DEFAULT_BOUNDS[k] for k in DEFAULT_VARY})
    start: dict = field(default_factory=dict)
    reference: dict = field(default_factory=dict)
    method: str = "nelder-mead"
    rays: int = 100_000
    sampler: str = "sobol"
    grid: int = 40
    evaluations: int = 600
    seconds: float | None = None
    seed: int = 0
    sigma0: float = 0.25
    popsize: int | None = None
    max_condition: float = 1e3
    region: float = 0.9
    confirm_rays: int = 1_000_000
    tolerance_rays: int = 400_000

    @classmethod
    def from_scene(cls, scene, **overrides) -> "DesignBrief":
        """The scene's ``design`` section, then ``overrides`` (``None`` values are ignored)."""
        names = {f.name for f in fields(cls)}
        brief = cls(**_design_section(dict(getattr(scene, "design", None) or {}),
                                      f"scene file {scene.source}: field design", names))
        over = {k: v for k, v in overrides.items() if v is not None}
        bad = set(over) - names
        if bad:
            raise UserError(f"optimize-lens: unknown settings {sorted(bad)}")
        if "constraints" in over:
            over["constraints"] = {**brief.constraints, **over["constraints"]}
        if "vary" in over:
            over["vary"] = {k: tuple(v) for k, v in over["vary"].items()}
        if "modes" in over:
            over["modes"] = tuple(over["modes"])
        brief = replace(brief, **over)
        brief.check()
        return brief

    def check(self) -> None:
        """One clear error for any inconsistent setting."""
        if self.objective not in OBJECTIVES:
            raise UserError(f"optimize-lens: objective must be one of {', '.join(OBJECTIVES)}, got {self.objective!r}")
        for k, v in self.constraints.items():
            if k not in CONSTRAINTS:
                raise UserError(f"optimize-lens: unknown constraint {k!r}; expected one of {', '.join(CONSTRAINTS)}")
            if v is not None and v != "bare" and not isinstance(v, (int, float)):
                raise UserError(f"optimize-lens: constraint {k} must be a number or 'bare', got {v!r}")
        needs_modes = OBJECTIVES[self.objective][0] in ("channel_cv", "valid_fraction", "median_condition") or any(
            CONSTRAINTS[k][0] in ("channel_cv", "valid_fraction", "median_condition")
            for k, v in self.constraints.items() if v is not None)
        if needs_modes and not self.modes:
            raise UserError("optimize-lens: the objective or a constraint needs lighting modes (--mode)")
        for k in list(self.vary) + list(self.start) + list(self.reference):
            if k not in PARAMETERS:
                raise UserError(f"optimize-lens: unknown parameter {k!r}; expected one of {', '.join(PARAMETERS)}")
        for name in ("rays", "grid", "evaluations", "confirm_rays", "tolerance_rays"):
            if int(getattr(self, name)) < 1:
                raise UserError(f"optimize-lens: {name} must be >= 1, got {getattr(self, name)}")
        if not 0 < self.sigma0 <= 1:
            raise UserError(f"optimize-lens: sigma0 must be in (0, 1], got {self.sigma0}")
        if not 0 < self.region <= 1.5:
            raise UserError(f"optimize-lens: region must be in (0, 1.5], got {self.region}")


#: How each key of a scene's ``design`` section becomes a :class:`DesignBrief` field.
_DESIGN_KEYS = {
    "objective": lambda v: v,
    "method": lambda v: v,
    "modes": tuple,
    "constraints": dict,
    "manufacturing": lambda v: Manufacturing(**v),
    "vary": lambda v: {k: tuple(float(x) for x in r) for k, r in v.items()},
    "start": lambda v: {k: float(x) for k, x in v.items()},
    "reference": lambda v: {k: float(x) for k, x in v.items()},
}


def _design_section(d: dict, where: str, names: set) -> dict:
    """:class:`DesignBrief` keyword arguments of a scene's ``design`` section (its ``search``
    keys are the brief's own fields)."""
    search = d.pop("search", {})
    unknown = sorted(set(d) - set(_DESIGN_KEYS))
    if unknown:
        raise UserError(f"{where}: unknown keys {unknown}")
    kw = {k: _DESIGN_KEYS[k](v) for k, v in d.items()}
    for k, v in search.items():
        if k not in names:
            raise UserError(f"{where}/search: unknown key {k!r}")
        kw[k] = v
    return kw
