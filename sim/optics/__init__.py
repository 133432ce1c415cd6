"""The optical ray tracer (paper §IV): surfaces, intersections, refraction, sampling, binning.

Modules: :mod:`~sim.optics.base` (convex-set base class), :mod:`~sim.optics.plane`,
:mod:`~sim.optics.sphere`, :mod:`~sim.optics.cylinder`, :mod:`~sim.optics.torus` (one per
surface geometry), :mod:`~sim.optics.lens` (the lens as one convex body),
:mod:`~sim.optics.paper_cases` (the paper's intersection cases 1-3),
:mod:`~sim.optics.quartic` (float64 quartic reference for the torus),
:mod:`~sim.optics.interface` (Snell, TIR, Fresnel), :mod:`~sim.optics.sampling`,
:mod:`~sim.optics.tracer` (chunked tracer), :mod:`~sim.optics.binning` (E and V),
:mod:`~sim.optics.multisource` (three ways to get every LED), :mod:`~sim.optics.instrument`.
"""
