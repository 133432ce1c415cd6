"""One solve path: frames of any source through the solver a name picks from the solver registry.

:class:`FrameSolver` is the path every eager solve takes (``reconstruct``, ``batch`` and
``run`` through the normals stage, ``live`` when no fast path applies): prepare the raw
frames (:class:`pipeline.normals.prepare.FramePrep`: dark level, saturation, markers, region),
solve them with :func:`solve_capture`, finish the results (scatter the region back, marker
pixels invalid). The fast per-frame paths take the same :class:`~pipeline.normals.prepare.FramePrep`
(:func:`pipeline.solving.frame_solvers.frame_solver`).

:func:`solve_capture` takes prepared frames ``(K, P, H, W, C)`` and a
:class:`~pipeline.normals.lights.LightSource`, checks that the lights are what the solver needs
(:func:`pipeline.normals.lights.check_lights`) and calls the solver's adapter: its
registry entry's target in :data:`pipeline.base.registry.SOLVERS`. Each adapter below turns
the stack into the solver's observations ``(P*C, H, W)`` (pattern-major, channel-minor) and
light vectors, per contact instance:

- :func:`stack_lstsq` (far field, :class:`pipeline.normals.farfield.FarFieldSolver`): the
  lights' far-field vectors (:meth:`~pipeline.normals.lights.LightSource.far_vectors`); a
  ``torch.compile``-d kernel with ``compile``;
- :func:`stack_nearfield` (:class:`pipeline.normals.nearfield.NearFieldSolver`): per-pixel
  light vectors (divided by the flat field first when the lights have one);
- :func:`stack_robust` (``robust``, :func:`pipeline.normals.robust_irls.solve_robust_irls`:
  explicit shadow and highlight models) and :func:`stack_cauchy` (``cauchy``, the earlier
  robust solver :func:`pipeline.normals.cauchy.solve_cauchy`): the light field if present,
  else the far field; dark values (within ``dark_threshold`` of the dark level) and saturated
  raw values are excluded;
- the calibration's fitted models (``far``, ``near``, ``traced``, ``lut``, ``mlp``): their
  adapters live in :mod:`pipeline.solving.model_solvers` (a model is a calibration object, a
  layer above this one) and call the model's batched ``normal_maps``.

A new solver is its module in ``pipeline/normals/`` plus an adapter with the signature of
these (``(frames, lights, **options) -> list[NormalResult]``), registered by one entry in
:data:`~pipeline.base.registry.SOLVERS` (``docs/developing.md`` lists every file).
"""

from __future__ import annotations

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.registry import SOLVERS
from pipeline.normals.lights import LightSource, check_lights
from pipeline.normals.prepare import FramePrep, full_scale

__all__ = ["FrameSolver", "solve_capture", "stack_lstsq", "stack_nearfield", "stack_robust",
           "stack_cauchy"]


class FrameSolver:
    """The eager solve path of a registered solver: prepare, solve, finish.

    Parameters
    ----------
    solver : str
        A name in :data:`pipeline.base.registry.SOLVERS`.
    lights : LightSource
        For the full frames (gathered here to the region's pixels).
    prep : FramePrep
        How the raw frames are prepared (its ``fills_markers`` and ``whole_frame`` are the
        solver's registry facts: :meth:`for_solver` builds it so).
    reference : ndarray, shape (P, H, W, C), optional
        Raw no-contact frames, prepared like the frames (the ratio and the calibration models
        read it).
    ratio, max_condition, device, dtype, compile
        As in :func:`solve_capture`.

    The frames' illumination drift (``prep.drift``, :meth:`~pipeline.normals.prepare.FramePrep.use_drift`)
    is taken against ``reference``, else against the one the solver's model stores (the LUT and
    the MLP keep their calibration's); ``auto`` removes it where the solver keys on the reference
    (registry fact ``info["keys_on_reference"]``, or ``ratio``).

    Examples
    --------
    >>> L = np.array([[[0, 0, 1.0]], [[0.6, 0, 0.8]], [[0, 0.6, 0.8]]])  # (P, C, 3)
    >>> fs = FrameSolver("lstsq", LightSource(far=L, source="doc"), FrameSolver.prep_for("lstsq", (2, 2)))
    >>> frames = np.broadcast_to((L[:, 0] @ [0, 0, 1.0])[:, None, None, None] * 100, (3, 2, 2, 1))
    >>> res = fs.solve(frames)
    >>> np.round(res.normals[0, 0], 6).tolist(), bool(res.mask.all())
    ([0.0, 0.0, 1.0], True)
    """

    def __init__(self, solver: str, lights: LightSource, prep: FramePrep, *, reference=None, ratio: bool = False,
                 max_condition: float = 1e3, device="cpu", dtype="float32", compile: bool = False):
        self.solver = SOLVERS.check(solver)
        self.prep = prep
        self.lights = prep.lights(lights)
        self.reference = prep.reference(reference)
        applies = bool(SOLVERS.get(self.solver).info.get("keys_on_reference")) or bool(ratio)
        if reference is not None:
            prep.use_drift(reference, applies=applies)
        else:
            prep.use_drift(lights.stored_reference(self.solver), applies=applies, linear=True)
        self.options = dict(ratio=bool(ratio), max_condition=float(max_condition), device=device, dtype=dtype,
                            compile=bool(compile),
                            dark_threshold=0.01 * prep.saturation if prep.saturation is not None else 0.0)
        self.method = "eager"

    @staticmethod
    def prep_for(solver: str, shape, *, raw_dtype=None, bit_depth: int | None = None, **kw) -> FramePrep:
        """The :class:`~pipeline.normals.prepare.FramePrep` of frames of ``shape`` for ``solver``
        (its registry entry says whether it fills markers itself and reads whole frames); with
        the raw frames' ``raw_dtype`` (and ``bit_depth``), values at full scale are flagged
        saturated (:func:`~pipeline.normals.prepare.full_scale`). ``kw``: the other
        :class:`~pipeline.normals.prepare.FramePrep` fields."""
        info = SOLVERS.get(solver).info
        saturation = None if raw_dtype is None else full_scale(raw_dtype, bit_depth)
        return FramePrep(shape, fills_markers=bool(info.get("fills_markers")), whole_frame=bool(info.get("whole_frame")),
                         saturation=saturation, **kw)

    def reset_drift(self) -> None:
        """The next frame's drift is fitted afresh (:meth:`~pipeline.normals.prepare.FramePrep.reset_drift`)."""
        self.prep.reset_drift()

    def solve_stack(self, raw, threads: int | None = 1) -> list:
        """Raw frames ``(K, P, H, W, C)`` -> one :class:`~pipeline.normals.result.NormalResult`
        per contact instance, with ``threads`` torch threads, or BLAS threads where the solve
        runs on numpy (:meth:`thread_limits`; None: the library's setting)."""
        from pipeline.base.threads import limit_threads

        frames, saturated = self.prep.frames(raw)
        with limit_threads(**self.thread_limits(threads)):
            res = solve_capture(frames, self.lights, solver=self.solver, reference=self.reference,
                                saturated=saturated, markers=self.prep.solver_markers, **self.options)
        return self.prep.finish(res)

    def thread_limits(self, threads: int | None) -> dict:
        """:func:`~pipeline.base.threads.limit_threads`'s arguments for a solve on ``threads``
        threads: BLAS's where the solver computes with numpy (registry fact
        ``info["numpy_on_cpu"]``, on the CPU without ``compile``: torch stays unimported),
        else torch's."""
        from pipeline.normals._xp import solve_device

        numpy_here = (bool(SOLVERS.get(self.solver).info.get("numpy_on_cpu"))
                      and solve_device(self.options["device"], self.options["compile"]) is None)
        return {"blas": threads} if numpy_here else {"torch": threads}

    def solve(self, frames, threads: int | None = 1):
        """One frame set ``(P, H, W, C)`` (or ``(H, W, C)``) -> its NormalResult."""
        f = np.asarray(frames)
        return self.solve_stack(f[None] if f.ndim == 4 else f[None, None], threads)[0]


def solve_capture(frames, lights: LightSource, *, solver: str = "lstsq", reference=None, saturated=None,
                  ratio: bool = False, max_condition: float = 1e3, dark_threshold: float = 0.0,
                  device="cpu", dtype="float32", compile: bool = False, markers=None) -> list:
    """Normals of every contact instance.

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        Dark-subtracted float frames.
    lights : LightSource
        The lights of the frames' pixels.
    solver : str
        A name in :data:`pipeline.base.registry.SOLVERS`.
    reference : ndarray, shape (P, H, W, C), optional
        Dark-subtracted no-contact frames (needed for ``ratio``).
    saturated : ndarray, shape (K, P, H, W, C), bool, optional
        Raw values at full scale; the robust solver excludes them.
    ratio : bool
        Divide by the reference first (:func:`pipeline.normals.ratio_to_reference`).
    max_condition, dark_threshold, device, dtype
        Passed to the solvers.
    compile : bool
        ``lstsq`` only: the ``torch.compile``-d far-field solver
        (:class:`pipeline.normals.FarFieldSolver`), for long recordings.
    markers : ndarray, shape (H, W), bool, optional
        Printed gel markers, for the calibration-model solvers (they fill them in themselves,
        as ``eval calibration`` does); the other solvers get frames already filled in by the
        normals stage and ignore it.

    Returns
    -------
    list of NormalResult
        One per contact instance.
    """
    entry = SOLVERS.get(solver)
    frames = np.asarray(frames, dtype=np.float32)
    _, P, _, _, C = frames.shape
    check_lights(solver, lights, P, C)
    return entry.load()(frames, lights, reference=reference, saturated=saturated, ratio=ratio,
                        max_condition=max_condition, dark_threshold=dark_threshold, device=device, dtype=dtype,
                        compile=compile, markers=markers)


def _observations(frames_k: np.ndarray) -> np.ndarray:
    """``(P, H, W, C)`` -> solver observations ``(P*C, H, W)`` (pattern-major, channel-minor)."""
    P, H, W, C = frames_k.shape
    return frames_k.transpose(0, 3, 1, 2).reshape(P * C, H, W)


def _per_contact(frames, L, flat, reference, ratio, solve_one, saturated=None) -> list:
    """``solve_one(obs (N, H, W), lights, k)`` for every contact ``k``, after the flat field and
    the optional ratio to the reference."""
    from pipeline.normals.ratio import ratio_to_reference

    ref = None if reference is None else _observations(np.asarray(reference, np.float32))
    if ratio and ref is None:
        raise UserError("--ratio needs the capture's reference frames")
    out = []
    for k in range(frames.shape[0]):
        obs = _observations(frames[k])
        if flat is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                obs = np.where(flat > 0, obs / np.where(flat > 0, flat, 1.0), np.nan)
        Lk = L
        if ratio:
            r_ref = ref if flat is None else ref / np.where(flat > 0, flat, 1.0)
            obs, Lk = ratio_to_reference(obs, r_ref, L)
        if saturated is not None:
            obs = np.where(_observations(saturated[k]), np.inf, obs)  # excluded as non-finite
        out.append(solve_one(obs, Lk))
    return out


def _flat(lights: LightSource, P: int, C: int, H: int, W: int):
    if lights.field is not None and lights.flat_field is not None:
        return lights.flat_field.reshape(P * C, H, W)
    return None


def _common(C: int, P: int, max_condition, device, dtype) -> dict:
    return dict(groups=np.tile(np.arange(C), P), max_condition=max_condition, device=device, dtype=dtype)


def stack_lstsq(frames, lights: LightSource, *, reference=None, ratio=False, max_condition=1e3, device="cpu",
                dtype="float32", compile=False, **_) -> list:
    """Far field: the lights' far-field vectors (the calibrated ones, else the light field at
    the image centre)."""
    from pipeline.normals.farfield import FarFieldSolver

    K, P, H, W, C = frames.shape
    L = lights.far_vectors().reshape(P * C, 3)
    common = _common(C, P, max_condition, device, dtype)
    prebuilt = None if ratio else FarFieldSolver(L, compile=compile, **common)
    return _per_contact(frames, L, None, reference, ratio,
                        lambda obs, Lk: (prebuilt if prebuilt is not None else FarFieldSolver(Lk, **common)).solve(obs))


def stack_nearfield(frames, lights: LightSource, *, reference=None, ratio=False, max_condition=1e3, device="cpu",
                    dtype="float32", **_) -> list:
    """Per-pixel light vectors (after the flat field, when the lights have one)."""
    from pipeline.normals.nearfield import NearFieldSolver

    K, P, H, W, C = frames.shape
    L = lights.field.reshape(P * C, H, W, 3)
    common = _common(C, P, max_condition, device, dtype)
    prebuilt = None if ratio else NearFieldSolver(L, **common)
    return _per_contact(frames, L, _flat(lights, P, C, H, W), reference, ratio,
                        lambda obs, Lk: (prebuilt if prebuilt is not None else NearFieldSolver(Lk, **common)).solve(obs))


def stack_robust(frames, lights: LightSource, **options) -> list:
    """Shadows and highlights modelled (:func:`pipeline.normals.robust_irls.solve_robust_irls`):
    the light field if present, else the far field; dark and saturated values excluded."""
    from pipeline.normals.robust_irls import solve_robust_irls

    return _robust(solve_robust_irls, frames, lights, **options)


def stack_cauchy(frames, lights: LightSource, **options) -> list:
    """The earlier robust solver (:func:`pipeline.normals.cauchy.solve_cauchy`: trimmed start,
    Cauchy IRLS), on the same observations as :func:`stack_robust`."""
    from pipeline.normals.cauchy import solve_cauchy

    return _robust(solve_cauchy, frames, lights, **options)


def _robust(robust, frames, lights: LightSource, *, reference=None, saturated=None, ratio=False, max_condition=1e3,
            dark_threshold=0.0, device="cpu", dtype="float32", **_) -> list:
    K, P, H, W, C = frames.shape
    L = lights.field.reshape(P * C, H, W, 3) if lights.field is not None else lights.far.reshape(P * C, 3)
    common = _common(C, P, max_condition, device, dtype)
    thr = dark_threshold if not ratio else 0.0
    return _per_contact(frames, L, _flat(lights, P, C, H, W), reference, ratio,
                        lambda obs, Lk: robust(obs, Lk, dark_threshold=thr, **common), saturated=saturated)
