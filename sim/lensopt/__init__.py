"""Lens optimisation (``iristac sim optimize-lens``; entry point :func:`sim.lens_design.optimize_lens`).

One idea per module: :mod:`~sim.lensopt.space` (the parameters and their bounds),
:mod:`~sim.lensopt.constraints` (what a workshop can make), :mod:`~sim.lensopt.objectives`
(figures of merit traced with common random numbers), :mod:`~sim.lensopt.search` (CMA-ES and
the methods it was measured against), :mod:`~sim.lensopt.tolerance` (+-0.1 mm),
:mod:`~sim.lensopt.brief` (the settings, from the scene file and the command line),
:mod:`~sim.lensopt.plot` (the trajectory figure), :mod:`~sim.lensopt.scene_file` (the winner
as a scene file).
"""
