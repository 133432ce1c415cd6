"""Stage 4, normals: per-pixel normals, albedo, residual, condition and mask of every contact instance.

Parameters that change the result, and so enter the key: the solver
(:data:`pipeline.base.registry.SOLVERS`), ``ratio``, ``max_condition``, the float type and
where the lights come from (``calibration``, ``illumination`` or the ``capture`` itself).
Inputs: the capture's identity and the light file's
(:func:`pipeline.stages.base.record_key`). The device, the thread count and ``compile`` do
not change the result and stay out of the key.

Where the lights come from (:func:`load_lights`, first that applies):

- ``calibration``: ``light_field (P, C, H, W, 3)`` (with optional ``flat_field (P, C, H, W)``
  by which observations are divided first), ``light_vectors (P, C, 3)`` (far field) and
  ``models/lut/*`` (the lookup table);
- ``illumination``: ``light_matrices (P, 3, H, W, 3)``, or ``V (L, H, W, 3)`` combined with
  the capture's ``drive``, ``brightness`` and ``exposure`` (and ``gains (L,)`` or ``(L, 3)``
  if the file has them) by :func:`sim.illumination_model.light_matrices`;
- the capture itself: ``lights/light_vectors (P, C, 3)`` (written by the DiLiGenT importer).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.registry import SOLVERS
from pipeline.stages.base import StageSpec, record_key

if TYPE_CHECKING:  # the solvers load torch: only when normals are computed
    from pipeline.normals.solve import LightSource

__all__ = ["SPEC", "load_lights", "params", "compute", "run", "node"]

SPEC = StageSpec("normals", version=1, schema="normals",
                 defaults={"solver": "lstsq", "ratio": False, "max_condition": 1e3, "dtype": "float32"})


def _check_shape(arr, want: tuple, path, name: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.shape != want:
        raise UserError(f"{path}: dataset {name!r} has shape {a.shape}, expected {want} to match the capture")
    return a


def load_lights(capture, calibration=None, illumination=None) -> LightSource:
    """Resolve the light model for ``capture`` (Records; see the module docstring)."""
    from pipeline.normals.solve import LightSource

    frames = capture.data["frames"]
    _, P, H, W, C = frames.shape
    if calibration is not None and illumination is not None:
        raise UserError("give either a calibration or an illumination file, not both")
    if calibration is not None:
        d, path = calibration.data, calibration.path
        src = LightSource(source=f"calibration:{Path(path).name if path else 'memory'}", key=record_key(calibration))
        if "light_field" in d:
            src.field = _check_shape(d["light_field"], (P, C, H, W, 3), path, "light_field")
            if "flat_field" in d:
                src.flat_field = _check_shape(d["flat_field"], (P, C, H, W), path, "flat_field")
        if "light_vectors" in d:
            src.far = _check_shape(d["light_vectors"], (P, C, 3), path, "light_vectors")
        lut = {k.split("/", 2)[2]: v for k, v in d.items() if k.startswith("models/lut/")}
        if lut:
            from calibration.models.lut import LookupTable

            try:
                src.table = LookupTable.from_arrays(lut)
            except KeyError as exc:
                raise UserError(f"{path}: lookup table is missing dataset models/lut/{exc.args[0]}") from None
        if src.field is None and src.far is None and src.table is None:
            raise UserError(f"{path}: calibration has no light model (expected dataset 'light_field', "
                            f"'light_vectors' or 'models/lut/*')")
        return src
    if illumination is not None:
        from sim.illumination_model import light_matrices

        d, path = illumination.data, illumination.path
        src = LightSource(source=f"illumination:{Path(path).name if path else 'memory'}",
                          key=record_key(illumination))
        if "light_matrices" in d and d["light_matrices"].shape[0] == P:
            src.field = _check_shape(d["light_matrices"], (P, C, H, W, 3), path, "light_matrices")
            return src
        V = np.asarray(d["V"])
        if V.shape[1:3] != (H, W):
            raise UserError(f"{path}: dataset 'V' covers {V.shape[1:3]} pixels, the capture has {(H, W)}")
        drive = capture.data["drive"]
        if drive.shape[1] != V.shape[0]:
            raise UserError(f"{path}: 'V' has {V.shape[0]} LEDs but the capture's drive has {drive.shape[1]}")
        if C != 3:
            raise UserError(f"{path}: illumination light matrices need 3 camera channels, the capture has {C}")
        gains = d.get("gains")
        src.field = light_matrices(V, drive, capture.data.get("brightness"),
                                   float(capture.meta.get("exposure", 1.0)), gains)
        return src
    if "lights/light_vectors" in capture.data:
        src = LightSource(source="capture:lights/light_vectors", key="embedded")
        src.far = _check_shape(capture.data["lights/light_vectors"], (P, C, 3), capture.path,
                               "lights/light_vectors")
        return src
    raise UserError(f"{capture.path}: no light model: pass --calibration or --illumination "
                    f"(the capture has no embedded lights/light_vectors)")


def params(*, solver: str = "lstsq", ratio: bool = False, max_condition: float = 1e3, dtype: str = "float32",
           lights: str) -> dict:
    """The key parameters; ``lights`` is ``calibration``, ``illumination`` or ``capture``.

    Examples
    --------
    >>> params(solver="nearfield", lights="illumination")["solver"]
    'nearfield'
    """
    return {"solver": SOLVERS.check(solver), "ratio": bool(ratio), "max_condition": float(max_condition),
            "dtype": str(dtype), "lights": str(lights)}


def _stack(results, name: str) -> np.ndarray:
    return np.stack([getattr(r, name) for r in results])


def compute(cap, lights: LightSource, *, solver: str = "lstsq", ratio: bool = False, max_condition: float = 1e3,
            device="cpu", dtype="float32", threads: int | None = 1, compile: bool = False):
    """The ``normals`` :class:`~pipeline.base.store.Record` of a capture (no caching).

    Parameters
    ----------
    cap : Record
        Schema ``capture``: ``frames (K, P, H, W, C)``, ``reference (P, H, W, C)``, optional
        ``dark (H, W, C)``; attributes ``mm_per_px`` and ``bit_depth``.
    lights : LightSource
        From :func:`load_lights`.
    solver, ratio, max_condition, device, dtype, threads, compile
        As in :func:`pipeline.reconstruct.reconstruct`.

    Returns
    -------
    Record
        Schema ``normals``: ``normals (K, H, W, 3)``, ``albedo``, ``residual``, ``condition``,
        ``mask``, ``count``.
    """
    from pipeline.base.store import Record
    from pipeline.base.threads import limit_threads
    from pipeline.normals.solve import solve_capture

    mm_per_px = float(cap.meta["mm_per_px"])
    raw = cap.data["frames"]
    frames = raw.astype(np.float32)
    ref = cap.data["reference"].astype(np.float32)
    if "dark" in cap.data:
        frames = frames - cap.data["dark"].astype(np.float32)
        ref = ref - cap.data["dark"].astype(np.float32)
    bits = cap.meta.get("bit_depth")
    full = (2 ** int(bits) - 1) if bits else (np.iinfo(raw.dtype).max if raw.dtype.kind in "iu" else None)
    saturated = (raw >= full) if full is not None else None
    dark_thr = 0.01 * full if full is not None else 0.0
    with limit_threads(torch=threads):
        res = solve_capture(frames, lights, solver=solver, reference=ref, saturated=saturated, ratio=ratio,
                            max_condition=max_condition, dark_threshold=dark_thr, device=device, dtype=dtype,
                            compile=compile)
    data = {name: _stack(res, name) for name in ("normals", "albedo", "residual", "condition", "mask", "count")}
    meta = {"solver": solver, "mm_per_px": mm_per_px, "ratio": bool(ratio), "max_condition": float(max_condition),
            "lights": lights.source, "valid_fraction": float(data["mask"].mean())}
    meta.update({k: v for k, v in res[0].meta.items() if k not in meta and isinstance(v, (str, int, float))})
    return Record("normals", data, meta)


def run(store, cap, cap_key, lights: LightSource, *, solver: str = "lstsq", ratio: bool = False,
        max_condition: float = 1e3, device="cpu", dtype="float32", threads: int | None = 1, compile: bool = False,
        force: bool = False, heal: bool = True):
    """``(record, key, cached)`` of the normals of ``cap`` (identified by ``cap_key``) through ``store``."""
    p = params(solver=solver, ratio=ratio, max_condition=max_condition, dtype=dtype,
               lights=lights.source.split(":")[0])
    return SPEC.get_or_compute(
        store, p, [cap_key, lights.key],
        lambda: compute(cap, lights, solver=solver, ratio=ratio, max_condition=max_condition, device=device,
                        dtype=dtype, threads=threads, compile=compile),
        force=force, heal=heal)


def node(config: Mapping[str, Any], ctx):
    """The graph node of a resolved run config's ``normals`` section (reads ``capture`` and the
    stage its ``lights`` name: ``calibrate`` or ``synthesize``)."""
    from pipeline.stages.graph import Stage

    p = config["normals"]
    ctx.need("normals", "capture")
    light_stage = "calibrate" if p["lights"] == "calibration" else "synthesize"
    ctx.need("normals", light_stage, f"with lights: {p['lights']}")

    def compute_node(inputs):
        cal = inputs.get("calibrate") if p["lights"] == "calibration" else None
        ill = inputs.get("synthesize") if p["lights"] == "illumination" else None
        lights = load_lights(inputs["capture"], cal, ill)
        return compute(inputs["capture"], lights, solver=p["solver"], ratio=bool(p["ratio"]),
                       max_condition=float(p["max_condition"]), device=ctx.device, dtype=p["dtype"])

    return Stage(SPEC.name, SPEC.version, params(**{k: p[k] for k in ("solver", "ratio", "max_condition", "dtype",
                                                                      "lights")}),
                 ["capture", light_stage], compute_node, schema=SPEC.schema)
