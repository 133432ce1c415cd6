"""Per-frame solvers for live use: the fast path a solver registers, else its eager solver.

:func:`frame_solver` builds, once per calibration (or illumination) and frame size, an object
whose ``solve(frames (P, H, W, C), threads=1) -> NormalResult`` reconstructs one integer
camera frame set. A solver whose registry entry names a fast path (``info["fast"]`` in
:data:`pipeline.base.registry.SOLVERS`) gets it; any other gets :class:`EagerFrameSolver`,
the same solver :func:`pipeline.normals.solve.solve_capture` runs for ``reconstruct``.

The fast paths (precomputed once, a compiled pass per frame; the eager solvers are their
references, ``tests/pipeline/normals/test_fast_paths.py``):

- ``nearfield`` and ``lstsq``: :class:`pipeline.normals.fast.NearFieldFast` on the light field
  (far field: the vectors at every pixel);
- ``lut``: :class:`pipeline.normals.fast_models.FastLUT` from the calibration's table, its
  per-bin position correction and tilt gain;
- ``mlp``: :class:`pipeline.normals.fast_models.FastMLP` from the calibration's network.

They live in the stage layer because the table and the network are calibration objects.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.registry import SOLVERS

__all__ = ["frame_solver", "EagerFrameSolver", "nearfield_fast", "lstsq_fast", "lut_fast", "mlp_fast"]


class EagerFrameSolver:
    """Any registered solver on one frame set at a time (the reference, and the fallback of
    solvers without a fast path).

    Parameters
    ----------
    solver : str
    lights : LightSource
    reference : ndarray, shape (P, H, W, C), optional
        No-contact frames (dark level removed).
    dark : ndarray, shape (H, W, C), optional
    markers : ndarray, shape (H, W), bool, optional
        Filled in before the solve (the calibration models do it themselves), invalid after.
    max_condition : float
    """

    def __init__(self, solver: str, lights, *, reference=None, dark=None, markers=None, max_condition: float = 1e3):
        self.solver = SOLVERS.check(solver)
        self.lights = lights
        self.reference = None if reference is None else np.asarray(reference, np.float32)
        self.dark = None if dark is None else np.asarray(dark, np.float32)
        self.markers = None if markers is None else np.asarray(markers, bool)
        self.max_condition = float(max_condition)
        self.model_fills = str(SOLVERS.get(solver).info.get("needs", "")).startswith("model:")
        self.method = "eager"

    def solve(self, frames, threads: int = 1):
        from pipeline.base.threads import limit_threads
        from pipeline.normals.solve import solve_capture

        f = np.asarray(frames, np.float32)
        if f.ndim == 3:
            f = f[None]
        if self.dark is not None:
            f = f - self.dark
        ref = self.reference
        if self.markers is not None and not self.model_fills:
            from calibration.markers import fill_markers

            f = fill_markers(f, self.markers)
            ref = None if ref is None else fill_markers(ref, self.markers)
        with limit_threads(torch=threads):
            res = solve_capture(f[None], self.lights, solver=self.solver, reference=ref,
                                max_condition=self.max_condition,
                                markers=self.markers if self.model_fills else None)[0]
        if self.markers is not None:
            res.mask = res.mask & ~self.markers
        return res


def nearfield_fast(lights, *, shape, channels: int, dark=None, max_condition: float = 1e3, region=None, **_):
    """:class:`~pipeline.normals.fast.NearFieldFast` of the light field (with its flat field)."""
    from pipeline.normals.fast import NearFieldFast

    if lights.field is None:
        raise UserError(f"--solver nearfield needs per-pixel lights; {lights.source} has none")
    P, C, H, W, _ = lights.field.shape
    flat = None if lights.flat_field is None else lights.flat_field.reshape(P * C, H, W)
    return NearFieldFast(lights.field.reshape(P * C, H, W, 3), groups=np.tile(np.arange(C), P), flat_field=flat,
                         max_condition=max_condition, mask=region, dark=dark)


def lstsq_fast(lights, *, shape, channels: int, dark=None, max_condition: float = 1e3, region=None, **_):
    """The far-field vectors (else the light field at the image centre, as ``lstsq`` takes them)
    at every pixel, through :class:`~pipeline.normals.fast.NearFieldFast`."""
    from pipeline.normals.fast import NearFieldFast

    H, W = shape
    far = lights.far if lights.far is not None else lights.field[:, :, H // 2, W // 2, :]
    P, C, _ = far.shape
    L = np.broadcast_to(far.reshape(P * C, 1, 1, 3), (P * C, H, W, 3))
    return NearFieldFast(L, groups=np.tile(np.arange(C), P), max_condition=max_condition, mask=region, dark=dark)


def _model(lights, name: str):
    model = (lights.models or {}).get(name)
    if model is None:
        raise UserError(f"--solver {name} needs a calibration with the '{name}' model; {lights.source} has "
                        f"{', '.join(lights.models or {}) or 'none'}")
    return model


def _reference(model, reference):
    ref = reference if reference is not None else model.stored_reference()
    if ref is None:
        raise UserError(f"the '{model.name}' model needs a no-contact reference frame")
    return np.asarray(ref, np.float32)


def lut_fast(lights, *, shape, dark=None, reference=None, markers=None, **_):
    """:class:`~pipeline.normals.fast_models.FastLUT` of the calibration's ``lut`` model."""
    from calibration.models.nearfield import poly_terms
    from pipeline.normals.fast_models import FastLUT

    model = _model(lights, "lut")
    t = model.table
    H, W = shape
    coef = phi = None
    if model.position_coef is not None:
        rows, cols = (a.ravel() for a in np.mgrid[:H, :W])
        coef, phi = model.position_coef, poly_terms(rows, cols, (H, W), model.position_degree)
    return FastLUT(t.lo, t.hi, t.table, t.filled, t.support, _reference(model, reference), coef=coef, phi=phi,
                   tilt_gain=model.tilt_gain, max_tilt=model.max_tilt, dark=dark, markers=markers)


def mlp_fast(lights, *, shape, dark=None, reference=None, markers=None, **_):
    """:class:`~pipeline.normals.fast_models.FastMLP` of the calibration's ``mlp`` model."""
    from calibration.models.nearfield import poly_terms
    from pipeline.normals.fast_models import FastMLP

    model = _model(lights, "mlp")
    members = []
    for net in model.nets:
        layers = [m for m in net if hasattr(m, "weight")]
        members.append([(m.weight.detach().cpu().numpy(), m.bias.detach().cpu().numpy()) for m in layers])
    H, W = shape
    uv = None
    if model.position:
        rows, cols = (a.ravel() for a in np.mgrid[:H, :W])
        uv = poly_terms(rows, cols, (H, W), model.position_degree)[:, 1:]
    return FastMLP(members, _reference(model, reference), uv, input_scale=model.input_scale, features=model.features,
                   tilt_gain=model.tilt_gain, max_tilt=model.max_tilt, dark=dark, markers=markers)


def frame_solver(solver: str, lights, *, shape, channels: int = 3, reference=None, dark=None, markers=None,
                 max_condition: float = 1e3, region=None, fast: bool = True) -> Any:
    """The per-frame solver of ``solver`` for frames of ``shape`` (H, W).

    Parameters
    ----------
    solver : str
        A name in :data:`pipeline.base.registry.SOLVERS`.
    lights : LightSource
        From :func:`pipeline.stages.normals.load_lights`.
    shape : (H, W)
    channels : int
    reference, dark, markers, max_condition
        As :class:`EagerFrameSolver`. Markers need filling in, which the fast paths do not do:
        with markers the eager solver is used.
    region : ndarray, shape (H, W), bool, optional
        Pixels to solve (fast near-field path only; the others solve every pixel).
    fast : bool
        False: always the eager solver.

    Returns
    -------
    object with ``solve(frames, threads=1) -> NormalResult`` and ``method`` (``fast``/``eager``).
    """
    entry = SOLVERS.get(solver)
    target = entry.info.get("fast")
    if fast and target and markers is None:
        from pipeline.base.registry import Entry

        build = Entry(f"{solver}-fast", target).load()
        out = build(lights, shape=tuple(shape), channels=channels, reference=reference, dark=dark,
                    max_condition=max_condition, region=region, markers=markers)
        out.method = "fast"
        return out
    return EagerFrameSolver(solver, lights, reference=reference, dark=dark, markers=markers,
                            max_condition=max_condition)
