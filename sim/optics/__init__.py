"""The optical ray tracer (paper §IV): surfaces, intersections, refraction, sampling, binning.

Modules: :mod:`~sim.optics.base` (convex-set base class), :mod:`~sim.optics.plane`,
:mod:`~sim.optics.sphere`, :mod:`~sim.optics.cylinder`, :mod:`~sim.optics.torus` (one per
surface geometry), :mod:`~sim.optics.lens` (the lens as one convex body),
:mod:`~sim.optics.paper_cases` (the paper's intersection cases 1-3),
:mod:`~sim.optics.quartic` (float64 quartic reference for the torus),
:mod:`~sim.optics.interface` (Snell, TIR, Fresnel), :mod:`~sim.optics.sampling`,
:mod:`~sim.optics.tracer` (the eager torch tracer, the reference), :mod:`~sim.optics.binning` (its
E and V accumulator), :mod:`~sim.optics.kernel` (the compiled per-ray kernel),
:mod:`~sim.optics.kernel_cuda` (the same on CUDA), :mod:`~sim.optics.engine` (which engine runs;
the kernel's driver), :mod:`~sim.optics.grid` (pixel grids, binning layouts, images; no torch),
:mod:`~sim.optics.emitter` (samplers and the LED frame; no torch), :mod:`~sim.optics.energy`
(energy books), :mod:`~sim.optics.multisource` (three ways to get every LED),
:mod:`~sim.optics.instrument`.
"""
