"""Per-frame solvers for live use: the fast path a solver registers, else its eager solve path.

:func:`frame_solver` builds, once per calibration (or illumination) and frame size, an object
whose ``solve(frames (P, H, W, C), threads=1) -> NormalResult`` reconstructs one integer
camera frame set. Both kinds take the same :class:`pipeline.normals.prepare.FramePrep` (dark
level, region, markers). A solver whose registry entry names a fast path (``info["fast"]`` in
:data:`pipeline.base.registry.SOLVERS`) gets it, unless markers must be filled in (the fast
paths do not fill them); any other gets :class:`pipeline.normals.solve.FrameSolver`, the
path ``reconstruct`` takes.

The fast paths (precomputed once, a compiled pass per frame; the eager solvers are their
references, ``tests/pipeline/normals/test_fast_paths.py``):

- ``nearfield`` and ``lstsq``: :class:`pipeline.normals.fast.NearFieldFast` on the light field
  (far field: the lights' far-field vectors at every pixel);
- ``lut``: :class:`pipeline.normals.fast_models.FastLUT` from the calibration's table, its
  per-bin position correction and tilt gain;
- ``mlp``: :class:`pipeline.normals.fast_models.FastMLP` from the calibration's network.

The LUT's and the MLP's fast paths also remove each frame's illumination drift against the
reference they key on (``drift``, :meth:`pipeline.normals.prepare.FramePrep.use_drift`: the
same estimator, the same sampled pixels as the eager path, applied inside the kernel). A drift
that varies over the image (``field``), or one asked for by name of a solver that does not key
on the reference, runs the eager path.

They live in the calibration layer because the table and the network are calibration objects.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.registry import SOLVERS

__all__ = ["frame_solver", "fast_nearfield", "fast_lstsq", "fast_lut", "fast_mlp"]


def fast_nearfield(lights, prep, *, max_condition: float = 1e3, **_):
    """:class:`~pipeline.normals.fast.NearFieldFast` of the light field (with its flat field)."""
    from pipeline.normals.fast import NearFieldFast

    if lights.field is None:
        raise UserError(f"--solver nearfield needs per-pixel lights; {lights.source} has none")
    P, C, H, W, _ = lights.field.shape
    flat = None if lights.flat_field is None else lights.flat_field.reshape(P * C, H, W)
    return NearFieldFast(lights.field.reshape(P * C, H, W, 3), groups=np.tile(np.arange(C), P), flat_field=flat,
                         max_condition=max_condition, mask=prep.region, dark=prep.dark)


def fast_lstsq(lights, prep, *, max_condition: float = 1e3, **_):
    """The lights' far-field vectors (:meth:`~pipeline.normals.lights.LightSource.far_vectors`)
    at every pixel, through :class:`~pipeline.normals.fast.NearFieldFast`."""
    from pipeline.normals.fast import NearFieldFast

    H, W = prep.shape
    far = lights.far_vectors()
    P, C, _ = far.shape
    L = np.broadcast_to(far.reshape(P * C, 1, 1, 3), (P * C, H, W, 3))
    return NearFieldFast(L, groups=np.tile(np.arange(C), P), max_condition=max_condition, mask=prep.region,
                         dark=prep.dark)


def _model(lights, name: str):
    model = (lights.models or {}).get(name)
    if model is None:
        raise UserError(f"--solver {name} needs a calibration with the '{name}' model; {lights.source} has "
                        f"{', '.join(lights.models or {}) or 'none'}")
    return model


def _reference(model, reference, prep):
    """The linear no-contact frames the model keys on: the raw ``reference`` minus the dark level
    (as :meth:`pipeline.normals.prepare.FramePrep.reference` prepares it for the eager path), else
    the model's own."""
    if reference is None:
        ref = model.stored_reference()
        if ref is None:
            raise UserError(f"the '{model.name}' model needs a no-contact reference frame")
        return np.asarray(ref, np.float32)
    ref = np.asarray(reference).astype(np.float32)
    return ref if prep.dark is None else ref - np.asarray(prep.dark).astype(np.float32)


def _drift(prep, solver: str, ref: np.ndarray):
    """The drift estimator against ``ref`` (the reference the kernel keys on) that ``prep.drift``
    resolves to for ``solver`` (:meth:`~pipeline.normals.prepare.FramePrep.use_drift`), or None."""
    prep.use_drift(ref, applies=bool(SOLVERS.get(solver).info.get("keys_on_reference")), linear=True)
    return prep.estimator


def fast_lut(lights, prep, *, reference=None, **_):
    """:class:`~pipeline.normals.fast_models.FastLUT` of the calibration's ``lut`` model."""
    from calibration.models.nearfield import poly_terms
    from pipeline.normals.fast_models import FastLUT

    model = _model(lights, "lut")
    t = model.table
    H, W = prep.shape
    coef = phi = None
    if model.position_coef is not None:
        rows, cols = (a.ravel() for a in np.mgrid[:H, :W])
        coef, phi = model.position_coef, poly_terms(rows, cols, (H, W), model.position_degree)
    ref = _reference(model, reference, prep)
    out = FastLUT(t.lo, t.hi, t.table, t.filled, t.support, ref, coef=coef, phi=phi, tilt_gain=model.tilt_gain,
                  max_tilt=model.max_tilt, dark=prep.dark, markers=prep.markers, drift=_drift(prep, "lut", ref))
    out.confidence_meaning = getattr(model, "confidence_meaning", None)
    return out


def fast_mlp(lights, prep, *, reference=None, **_):
    """:class:`~pipeline.normals.fast_models.FastMLP` of the calibration's ``mlp`` model."""
    from calibration.models.nearfield import poly_terms
    from pipeline.normals.fast_models import FastMLP

    model = _model(lights, "mlp")
    members = []
    for net in model.nets:
        layers = [m for m in net if hasattr(m, "weight")]
        members.append([(m.weight.detach().cpu().numpy(), m.bias.detach().cpu().numpy()) for m in layers])
    H, W = prep.shape
    uv = None
    if model.position:
        rows, cols = (a.ravel() for a in np.mgrid[:H, :W])
        uv = poly_terms(rows, cols, (H, W), model.position_degree)[:, 1:]
    ref = _reference(model, reference, prep)
    out = FastMLP(members, ref, uv, input_scale=model.input_scale, features=model.features,
                  tilt_gain=model.tilt_gain, max_tilt=model.max_tilt, dark=prep.dark, markers=prep.markers,
                  drift=_drift(prep, "mlp", ref))
    out.confidence_meaning = getattr(model, "confidence_meaning", None)
    return out


def frame_solver(solver: str, lights, *, shape, channels: int = 3, reference=None, dark=None, markers=None,
                 max_condition: float = 1e3, region=None, fast: bool = True, drift: str = "auto",
                 drift_samples: int | None = None, drift_every: int | None = None, raw_dtype=None,
                 bit_depth: int | None = None, name: str = "live", **eager) -> Any:
    """The per-frame solver of ``solver`` for frames of ``shape`` (H, W).

    Parameters
    ----------
    solver : str
        A name in :data:`pipeline.base.registry.SOLVERS`.
    lights : LightSource
        From :func:`pipeline.solving.light_files.load_lights`.
    shape : (H, W)
    channels : int
    reference : ndarray, shape (P, H, W, C), optional
        Raw no-contact frames, the dark level not removed (the calibration models key on the
        change against them); None: the model's own.
    dark : ndarray, shape (H, W, C), optional
    markers : ndarray, shape (H, W), bool, optional
        Printed gel markers. Filling them in is the eager path's (the fast paths do not):
        with markers the eager solver is used.
    max_condition : float
    region : ndarray, shape (H, W), bool, optional
        Pixels to solve (the fast near-field path reads only them; the others solve every
        pixel and mark the rest invalid).
    fast : bool
        False: always the eager solver.
    drift : str
        The illumination drift removed from each frame (``auto``: against the reference the
        solver keys on, for the LUT and the MLP; :meth:`pipeline.normals.prepare.FramePrep.use_drift`),
        fitted on :data:`pipeline.normals.drift.LIVE_SAMPLES` pixels of every
        :data:`~pipeline.normals.drift.LIVE_REFIT_EVERY`-th frame (fast and eager alike;
        ``reset_drift()`` fits the next frame).
    drift_samples, drift_every : int, optional
        Instead of the live defaults: a recording's frames are separate presses, each fitted
        on :data:`pipeline.normals.drift.SAMPLES` pixels (what the normals stage does), so the
        fast and the eager paths give the same numbers.
    raw_dtype, bit_depth, name
        The frames' integer type and bit depth (the eager path flags values at full scale as
        saturated, as the normals stage does) and their name in messages.
    **eager
        ``ratio``, ``device``, ``dtype``, ``compile`` of :class:`pipeline.normals.solve.FrameSolver`:
        any but their defaults (no ratio, the CPU, float32) takes the eager path.

    Returns
    -------
    object with ``solve(frames, threads=1) -> NormalResult`` and ``method`` (``fast``/``eager``).
    """
    from pipeline.normals.drift import LIVE_REFIT_EVERY, LIVE_SAMPLES
    from pipeline.normals.solve import FrameSolver

    prep = FrameSolver.prep_for(solver, shape, raw_dtype=raw_dtype, bit_depth=bit_depth, dark=dark, markers=markers,
                                region=region, name=name, drift=drift,
                                drift_samples=LIVE_SAMPLES if drift_samples is None else int(drift_samples),
                                drift_every=LIVE_REFIT_EVERY if drift_every is None else int(drift_every))
    keys = bool(SOLVERS.get(solver).info.get("keys_on_reference"))
    fast_drift = drift in ("auto", "none") or (keys and drift in ("offset", "gain_offset"))
    plain = (not eager.get("ratio") and str(eager.get("device", "cpu")) == "cpu"
             and str(eager.get("dtype", "float32")) == "float32" and not eager.get("compile")
             and (raw_dtype is None or np.dtype(raw_dtype).kind in "ui"))
    build = SOLVERS.fast(solver) if fast and markers is None and fast_drift and plain else None
    if build is not None:
        out = build(lights, prep, channels=channels, reference=reference, max_condition=max_condition)
        out.method = "fast"
        return out
    return FrameSolver(solver, lights, prep, reference=reference, max_condition=max_condition, **eager)
