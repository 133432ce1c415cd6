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

Where to solve (:func:`capture_region`): the capture's ``mask`` dataset (an object's
silhouette: DiLiGenT's, ``iristac sim ps-object``'s), or a user's ``mask`` (``--mask``), which
replaces it and enters the key. Only those pixels are read out of the frames and solved
(:class:`pipeline.normals.masking.PixelMask`); every pixel outside is invalid in the record.
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

__all__ = ["SPEC", "load_lights", "capture_region", "reference_frames", "params", "compute", "run", "node"]

SPEC = StageSpec("normals", version=2, schema="normals",  # 2: only the capture's (or user's) mask is solved
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
        name = Path(capture.path).name if capture.path else "memory"
        src = LightSource(source=f"capture:{name}:lights/light_vectors", key="embedded")
        src.far = _check_shape(capture.data["lights/light_vectors"], (P, C, 3), capture.path,
                               "lights/light_vectors")
        return src
    raise UserError(f"{capture.path}: no light model: pass --calibration or --illumination "
                    f"(the capture has no embedded lights/light_vectors)")


def capture_region(cap, mask=None) -> np.ndarray | None:
    """The pixels to reconstruct: a user's ``mask`` (a ``.png``/``.npy`` path or an array), else
    the capture's ``mask`` dataset, else None (every pixel).

    Raises
    ------
    UserError
        Naming the mask file (or the capture and its dataset ``mask``) when the mask does not
        have the frames' ``(H, W)`` or selects no pixel.
    """
    import os

    H, W = cap.data["frames"].shape[2:4]
    if mask is None:
        if "mask" not in cap.data:
            return None
        m, where = np.asarray(cap.data["mask"]), f"{cap.path or 'capture'}: dataset 'mask'"
    elif isinstance(mask, (str, os.PathLike)):
        from pipeline.evaluate import load_mask

        m, where = load_mask(mask), f"{mask}: mask"
    else:
        m, where = np.asarray(mask), "mask"
    if m.shape != (H, W):
        raise UserError(f"{where} has shape {m.shape}, expected (H, W) = {(H, W)} to match the capture's frames")
    if m.dtype != bool:
        m = m != 0
    if not m.any():
        raise UserError(f"{where} selects no pixels (all zero): nothing to reconstruct")
    return m


def reference_frames(cap) -> np.ndarray | None:
    """The capture's no-contact ``reference (P, H, W, C)``, or None when it has none (the
    dataset is absent, or a version-1 file marked ``has_reference = False`` holds zeros)."""
    if "reference" not in cap.data or cap.meta.get("has_reference", True) is False:
        return None
    return cap.data["reference"]


def params(*, solver: str = "lstsq", ratio: bool = False, max_condition: float = 1e3, dtype: str = "float32",
           lights: str, mask=None) -> dict:
    """The key parameters; ``lights`` is ``calibration``, ``illumination`` or ``capture``;
    ``mask``, a user's region (the capture's own is part of the capture's identity), enters
    as its digest.

    Examples
    --------
    >>> params(solver="nearfield", lights="illumination")["solver"]
    'nearfield'
    """
    p = {"solver": SOLVERS.check(solver), "ratio": bool(ratio), "max_condition": float(max_condition),
         "dtype": str(dtype), "lights": str(lights)}
    if mask is not None:
        from pipeline.base.hashing import digest

        p["mask"] = digest(np.asarray(mask, bool))
    return p


def _stack(results, name: str) -> np.ndarray:
    return np.stack([getattr(r, name) for r in results])


def compute(cap, lights: LightSource, *, solver: str = "lstsq", ratio: bool = False, max_condition: float = 1e3,
            device="cpu", dtype="float32", threads: int | None = 1, compile: bool = False, mask=None):
    """The ``normals`` :class:`~pipeline.base.store.Record` of a capture (no caching).

    Parameters
    ----------
    cap : Record
        Schema ``capture``: ``frames (K, P, H, W, C)``, optional ``reference (P, H, W, C)``,
        ``dark (H, W, C)`` and ``mask (H, W)``; attributes ``mm_per_px`` and ``bit_depth``.
    lights : LightSource
        From :func:`load_lights`.
    solver, ratio, max_condition, device, dtype, threads, compile
        As in :func:`pipeline.reconstruct.reconstruct`.
    mask : path or ndarray, shape (H, W), optional
        The pixels to solve, replacing the capture's ``mask`` (:func:`capture_region`). Only
        they are read out of the frames and solved; the others are invalid in the result.

    Returns
    -------
    Record
        Schema ``normals``: ``normals (K, H, W, 3)``, ``albedo``, ``residual``, ``condition``,
        ``mask``, ``count``.
    """
    from pipeline.base.store import Record
    from pipeline.base.threads import limit_threads
    from pipeline.normals.masking import PixelMask
    from pipeline.normals.solve import solve_capture

    mm_per_px = float(cap.meta["mm_per_px"])
    raw = cap.data["frames"]
    H, W = raw.shape[2:4]
    region = capture_region(cap, mask)
    ref = reference_frames(cap)
    dark = cap.data.get("dark")
    pixels = None
    if region is not None and SOLVERS.get(solver).info.get("needs") != "table":
        # Gather the region once, from the raw frames (no full-frame float copy), as a (1, M)
        # image; the solvers then see only its pixels. (A lookup table needs whole frames:
        # it is masked after.)
        pixels = PixelMask(region, (H, W), f"{cap.path or 'capture'}: mask")
        raw = pixels.gather(raw, axis=2)
        ref = None if ref is None else pixels.gather(ref, axis=1)
        dark = None if dark is None else pixels.gather(dark, axis=0)
        lights = _gather_lights(lights, pixels, solver)
    frames = raw.astype(np.float32)
    ref = None if ref is None else ref.astype(np.float32)
    if dark is not None:
        frames = frames - dark.astype(np.float32)
        ref = None if ref is None else ref - dark.astype(np.float32)
    bits = cap.meta.get("bit_depth")
    full = (2 ** int(bits) - 1) if bits else (np.iinfo(raw.dtype).max if raw.dtype.kind in "iu" else None)
    saturated = (raw >= full) if full is not None else None
    dark_thr = 0.01 * full if full is not None else 0.0
    with limit_threads(torch=threads):
        res = solve_capture(frames, lights, solver=solver, reference=ref, saturated=saturated, ratio=ratio,
                            max_condition=max_condition, dark_threshold=dark_thr, device=device, dtype=dtype,
                            compile=compile)
    if pixels is not None:
        res = [pixels.scatter(r) for r in res]
    elif region is not None:
        res = [PixelMask(region, (H, W)).restrict(r) for r in res]
    data = {name: _stack(res, name) for name in ("normals", "albedo", "residual", "condition", "mask", "count")}
    meta = {"solver": solver, "mm_per_px": mm_per_px, "ratio": bool(ratio), "max_condition": float(max_condition),
            "lights": lights.source, "valid_fraction": float(data["mask"].mean())}
    if region is not None:
        meta["region_pixels"] = int(region.sum())
    meta.update({k: v for k, v in res[0].meta.items() if k not in meta and isinstance(v, (str, int, float))})
    return Record("normals", data, meta)


def _gather_lights(lights: LightSource, pixels, solver: str) -> LightSource:
    """``lights`` on the gathered pixels (per-pixel fields gathered; far-field unchanged)."""
    from dataclasses import replace

    far = lights.far
    if far is None and lights.field is not None and solver == "lstsq":
        # lstsq uses the light field at the image centre: take it before the centre is gone.
        H, W = pixels.shape
        far = lights.field[:, :, H // 2, W // 2, :]
    return replace(lights, far=far,
                   field=None if lights.field is None else pixels.gather(lights.field, axis=2),
                   flat_field=None if lights.flat_field is None else pixels.gather(lights.flat_field, axis=2))


def run(store, cap, cap_key, lights: LightSource, *, solver: str = "lstsq", ratio: bool = False,
        max_condition: float = 1e3, device="cpu", dtype="float32", threads: int | None = 1, compile: bool = False,
        force: bool = False, heal: bool = True, mask=None):
    """``(record, key, cached)`` of the normals of ``cap`` (identified by ``cap_key``) through
    ``store``; ``mask``: a user's region (an array, see :func:`capture_region`) instead of the
    capture's."""
    p = params(solver=solver, ratio=ratio, max_condition=max_condition, dtype=dtype,
               lights=lights.source.split(":")[0], mask=mask)
    return SPEC.get_or_compute(
        store, p, [cap_key, lights.key],
        lambda: compute(cap, lights, solver=solver, ratio=ratio, max_condition=max_condition, device=device,
                        dtype=dtype, threads=threads, compile=compile, mask=mask),
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
