"""Photometric stereo solvers: per-pixel normals, albedo, residual, condition and mask.

One module per solver, all batched over pixels in torch (``device=`` picks CPU or CUDA), except
that the far-field solve computes with numpy on the CPU (the same code,
:mod:`pipeline.normals._xp`: a one-shot ``reconstruct --solver lstsq`` does not import torch):

- :class:`FarFieldSolver` / :func:`solve_farfield` (``lstsq``): Woodham, one light vector
  per observation, precomputed pseudo-inverse;
- :class:`NearFieldSolver` / :func:`solve_nearfield` (``nearfield``): per-pixel light
  vectors, normal equations or QR;
- :func:`solve_robust_irls` (``robust``): explicit attached-shadow, cast-shadow and highlight
  models, IRLS with Tukey weights from a trimmed start;
- :func:`solve_cauchy` (``cauchy``): the earlier robust solver: excludes dark/saturated
  observations, then Cauchy IRLS (or trim);
- :func:`ratio_to_reference`: optional preprocessing that cancels albedo and vignetting;
- :class:`PixelMask`, :func:`masked_solve`: every solver's ``mask=`` (gather the masked pixels,
  solve them, scatter back with the rest invalid).

:class:`pipeline.normals.solve.FrameSolver` is the one path from raw frames to normals with the
solver a name picks from the registry (:data:`pipeline.base.registry.SOLVERS`, where a new
solver is registered): frames prepared by :class:`pipeline.normals.prepare.FramePrep`, lights
from :class:`pipeline.normals.lights.LightSource`.

Observations are ``(N_obs, H, W)`` (patterns x channels flattened), lights ``(N_obs, 3)`` or
``(N_obs, H, W, 3)``. Every result is a :class:`NormalResult` with finite arrays.
"""

from pipeline.base.lazy import lazy_names

# Names are imported on first use (PEP 562): the solvers load torch, and the live fast paths
# (``pipeline.normals.fast``, Numba) must not pay for it (about a second of a live start).
_WHERE = {"FarFieldSolver": "farfield", "solve_farfield": "farfield",
          "PixelMask": "masking", "masked_solve": "masking", "NearFieldSolver": "nearfield",
          "solve_nearfield": "nearfield", "ratio_to_reference": "ratio", "NormalResult": "result",
          "solve_cauchy": "cauchy", "solve_robust_irls": "robust_irls"}
__getattr__, __dir__ = lazy_names(__name__, _WHERE, globals())

__all__ = ["NormalResult", "FarFieldSolver", "solve_farfield", "NearFieldSolver", "solve_nearfield",
           "solve_cauchy", "solve_robust_irls", "ratio_to_reference", "PixelMask",
           "masked_solve"]
