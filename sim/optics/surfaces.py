"""The lens surfaces: which class traces each with the torch reference, and which engines trace it.

A lens (:class:`sim.scene.Lens`) is a side, a top and a bottom; :func:`lens_surfaces` names the
surface kind of each, and :data:`SURFACES` says, per kind, the :class:`~sim.optics.base.ConvexSet`
the torch tracer uses (:class:`sim.optics.lens.LensBody`) and the engines that trace it
(:data:`sim.optics.engine.ENGINES`). The compiled kernel (:mod:`sim.optics.kernel`) implements
the swept arc, the cylinder, the sphere and the plane; a surface it does not trace is traced by
``torch``, and :func:`sim.optics.engine.resolve_engine` says so when it falls back.

This module imports no torch: the engine choice reads it before any tracer is loaded.

Examples
--------
>>> from sim.scene import load_scene
>>> lens_surfaces(load_scene("default").lens), engines_for(("swept_arc", "conic", "plane"))
(('swept_arc', 'sphere', 'plane'), ('torch',))
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["SurfaceKind", "SURFACES", "lens_surfaces", "engines_for"]


@dataclass(frozen=True)
class SurfaceKind:
    """One kind of lens surface.

    Attributes
    ----------
    name : str
    part : {"side", "top", "bottom"}
        Where on the lens it may stand.
    target : str
        ``"module:Class"`` of its :class:`~sim.optics.base.ConvexSet` (the torch tracer's).
    engines : tuple of str
        The engines that trace it.
    """

    name: str
    part: str
    target: str
    engines: tuple[str, ...]


#: Every surface kind a lens can have, by name.
SURFACES = {s.name: s for s in (
    SurfaceKind("swept_arc", "side", "sim.optics.torus:SweptArc", ("kernel", "torch")),
    SurfaceKind("cylinder", "side", "sim.optics.cylinder:Cylinder", ("kernel", "torch")),
    SurfaceKind("sphere", "top", "sim.optics.sphere:Ball", ("kernel", "torch")),
    SurfaceKind("conic", "top", "sim.optics.conic:ConicTop", ("torch",)),
    SurfaceKind("plane", "bottom", "sim.optics.plane:HalfSpaceAbove", ("kernel", "torch")),
)}


def lens_surfaces(lens) -> tuple[str, str, str]:
    """The ``(side, top, bottom)`` surface kinds of a :class:`sim.scene.Lens`."""
    side = "swept_arc" if lens.is_arc else "cylinder"
    top = "sphere" if lens.top_conic == 0.0 else "conic"
    return side, top, "plane"


def engines_for(surfaces) -> tuple[str, ...]:
    """The engines that trace every one of ``surfaces`` (names in :data:`SURFACES`), in the
    order of :data:`sim.optics.engine.ENGINES`."""
    out = ("kernel", "torch")
    for name in surfaces:
        out = tuple(e for e in out if e in SURFACES[name].engines)
    return out
