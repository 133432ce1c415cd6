"""Normals of a capture's frame stack with the solver a name picks from the solver registry.

:func:`solve_capture` takes dark-subtracted frames ``(K, P, H, W, C)`` and a
:class:`LightSource`, checks that the lights are what the solver needs
(:data:`pipeline.base.registry.SOLVERS`, ``info["needs"]`` and ``info["patterns"]``) and calls
the solver's adapter. Each adapter below turns the stack into the solver's observations
``(P*C, H, W)`` (pattern-major, channel-minor) and light vectors, per contact instance:

- :func:`solve_lstsq` (far field): the far-field vectors, else the light field at the image
  centre (what a far-field calibration would measure there); a ``torch.compile``-d kernel
  with ``compile``;
- :func:`solve_nearfield`: per-pixel light vectors (divided by the flat field first when the
  lights have one);
- :func:`solve_robust` (``robust``, :func:`pipeline.normals.robust_irls.solve_robust_irls`:
  explicit shadow and highlight models) and :func:`solve_cauchy` (``cauchy``, the earlier
  robust solver :func:`pipeline.normals.robust.solve_robust`): the light field if present, else
  the far field; dark values (within ``dark_threshold`` of the dark level) and saturated raw
  values are excluded;
- the calibration's fitted models (``far``, ``near``, ``traced``, ``lut``, ``mlp``): their
  adapters live in :mod:`pipeline.stages.model_solvers` (a model is a calibration object, a
  layer above this one) and call the model's batched ``normal_maps``.

A new solver is its module in ``pipeline/normals/`` plus an adapter with the signature of
these (``(frames, lights, **options) -> list[NormalResult]``), registered by one entry in
:data:`~pipeline.base.registry.SOLVERS`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.registry import SOLVERS

__all__ = ["LightSource", "solve_capture", "solve_lstsq", "solve_nearfield", "solve_robust", "solve_cauchy",
           "applicable_solvers"]


@dataclass
class LightSource:
    """The light model a reconstruction uses.

    Attributes
    ----------
    far : ndarray, shape (P, C, 3), optional
        One light vector per pattern-channel.
    field : ndarray, shape (P, C, H, W, 3), optional
        Per-pixel light vectors.
    flat_field : ndarray, shape (P, C, H, W), optional
        Observations are divided by it before solving (goes with ``field``).
    models : dict, optional
        A calibration's fitted models, name -> object with ``normal_maps(frames, reference,
        markers=...)`` (:func:`calibration.stored.calibration_from_record`).
    markers : ndarray, shape (H, W), bool, optional
        The printed gel markers the calibration found (the default marker mask of frames
        reconstructed with it).
    source : str
        Where the lights came from (for the record's attributes).
    key : str
        Identity of the light file (enters the normals stage key).
    """

    far: np.ndarray | None = None
    field: np.ndarray | None = None
    flat_field: np.ndarray | None = None
    models: dict[str, Any] | None = None
    markers: np.ndarray | None = None
    source: str = ""
    key: str = ""

    def kinds(self) -> set[str]:
        """What these lights offer, in the terms of a solver's ``needs``."""
        out = set()
        if self.far is not None or self.field is not None:
            out.add("vectors")
        if self.field is not None:
            out.add("field")
        out.update(f"model:{name}" for name in (self.models or {}))
        return out


def applicable_solvers(patterns: int, channels: int, kinds: set[str], variants: bool = False) -> tuple[str, ...]:
    """The registered solvers that can solve ``patterns`` x ``channels`` observations with lights
    offering ``kinds`` (:meth:`LightSource.kinds`), in registry order; ``variants`` includes the
    entries marked as alternatives (``info["variant"]``).

    Examples
    --------
    >>> applicable_solvers(24, 3, {"vectors", "field"})
    ('lstsq', 'nearfield', 'robust')
    >>> applicable_solvers(1, 3, {"vectors", "field", "model:lut"})
    ('lstsq', 'nearfield', 'robust', 'lut')
    """
    return tuple(e.name for e in SOLVERS if e.info.get("needs") in kinds
                 and (variants or not e.info.get("variant"))
                 and (e.info.get("patterns", "any") != "one-rgb" or (patterns == 1 and channels == 3)))


def _check_lights(solver: str, lights: LightSource, P: int, C: int) -> None:
    info = SOLVERS.get(solver).info
    needs = info.get("needs") or ""
    if needs.startswith("model:") and needs[6:] not in (lights.models or {}):
        have = ", ".join(lights.models or {}) or "none"
        what = {"lut": "the lookup table", "mlp": "the MLP", "far": "the far-field model",
                "near": "the near-field model", "traced": "the traced model"}.get(needs[6:], "the model")
        raise UserError(f"--solver {solver} needs a calibration with {what} fitted (models/{needs[6:]}/*); "
                        f"{lights.source or 'the light source'} has {have} (fit it with iristac calibrate --model)")
    if info.get("patterns") == "one-rgb" and (P != 1 or C != 3):
        raise UserError(f"--solver {solver} needs one RGB pattern per frame, the capture has P={P}, C={C}")
    if needs == "field" and lights.field is None:
        raise UserError(f"--solver {solver} needs per-pixel lights (an illumination file or a calibration "
                        f"with light_field); {lights.source} has only far-field light vectors")
    if needs in ("vectors", "field") and lights.field is None and lights.far is None:
        raise UserError(f"--solver {solver} needs light vectors; {lights.source} has only fitted models "
                        f"({', '.join(lights.models or {})}): use --solver with one of them")
    if needs in ("vectors", "field"):
        _check_light_count(None if lights.far is None else lights.far.reshape(P * C, 3), P, C,
                           lights.source or "the light source")


def _check_light_count(far, P: int, C: int, source: str) -> None:
    """One clear error when the lights cannot determine a normal anywhere: fewer than three
    observations, or far-field light vectors ``far (P*C, 3)`` (None: per-pixel lights only)
    that span fewer than three directions."""
    if P * C < 3:
        raise UserError(f"{source}: {P} pattern(s) x {C} channel(s) = {P * C} observations; photometric stereo "
                        f"needs at least 3 lights")
    if far is not None:
        L = np.asarray(far)
        ok = np.isfinite(L).all(-1)
        sv = np.linalg.svd(L[ok].astype(np.float64), compute_uv=False) if ok.any() else np.zeros(1)
        rank = int((sv > 1e-6 * sv.max()).sum()) if sv.max() > 0 else 0  # 1e-6: float32-stored lights
        if rank < 3:
            raise UserError(f"{source}: the {P * C} light vectors span {rank} independent direction(s); "
                            f"photometric stereo needs at least 3 lights in different directions")


def solve_capture(frames, lights: LightSource, *, solver: str = "lstsq", reference=None, saturated=None,
                  ratio: bool = False, max_condition: float = 1e3, dark_threshold: float = 0.0,
                  device="cpu", dtype="float32", compile: bool = False, markers=None) -> list:
    """Normals of every contact instance.

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        Dark-subtracted float frames.
    lights : LightSource
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
    _check_lights(solver, lights, P, C)
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


def solve_lstsq(frames, lights: LightSource, *, reference=None, ratio=False, max_condition=1e3, device="cpu",
                dtype="float32", compile=False, **_) -> list:
    """Far field: the calibrated vectors, else the light field at the image centre."""
    from pipeline.normals.farfield import FarFieldSolver

    K, P, H, W, C = frames.shape
    far = lights.far if lights.far is not None else lights.field[:, :, H // 2, W // 2, :]
    L = far.reshape(P * C, 3)
    common = _common(C, P, max_condition, device, dtype)
    prebuilt = None if ratio else FarFieldSolver(L, compile=compile, **common)
    return _per_contact(frames, L, None, reference, ratio,
                        lambda obs, Lk: (prebuilt if prebuilt is not None else FarFieldSolver(Lk, **common)).solve(obs))


def solve_nearfield(frames, lights: LightSource, *, reference=None, ratio=False, max_condition=1e3, device="cpu",
                    dtype="float32", **_) -> list:
    """Per-pixel light vectors (after the flat field, when the lights have one)."""
    from pipeline.normals.nearfield import NearFieldSolver

    K, P, H, W, C = frames.shape
    L = lights.field.reshape(P * C, H, W, 3)
    common = _common(C, P, max_condition, device, dtype)
    prebuilt = None if ratio else NearFieldSolver(L, **common)
    return _per_contact(frames, L, _flat(lights, P, C, H, W), reference, ratio,
                        lambda obs, Lk: (prebuilt if prebuilt is not None else NearFieldSolver(Lk, **common)).solve(obs))


def solve_robust(frames, lights: LightSource, **options) -> list:
    """Shadows and highlights modelled (:func:`pipeline.normals.robust_irls.solve_robust_irls`):
    the light field if present, else the far field; dark and saturated values excluded."""
    from pipeline.normals.robust_irls import solve_robust_irls

    return _robust(solve_robust_irls, frames, lights, **options)


def solve_cauchy(frames, lights: LightSource, **options) -> list:
    """The earlier robust solver (:func:`pipeline.normals.robust.solve_robust`: trimmed start,
    Cauchy IRLS), on the same observations as :func:`solve_robust`."""
    from pipeline.normals.robust import solve_robust as cauchy

    return _robust(cauchy, frames, lights, **options)


def _robust(robust, frames, lights: LightSource, *, reference=None, saturated=None, ratio=False, max_condition=1e3,
            dark_threshold=0.0, device="cpu", dtype="float32", **_) -> list:
    K, P, H, W, C = frames.shape
    L = lights.field.reshape(P * C, H, W, 3) if lights.field is not None else lights.far.reshape(P * C, 3)
    common = _common(C, P, max_condition, device, dtype)
    thr = dark_threshold if not ratio else 0.0
    return _per_contact(frames, L, _flat(lights, P, C, H, W), reference, ratio,
                        lambda obs, Lk: robust(obs, Lk, dark_threshold=thr, **common), saturated=saturated)
