"""Stages 4 and 5 from files: a capture and its lights -> ``normals.h5`` and ``depth.h5``.

:func:`reconstruct` is the function behind ``iristac reconstruct``. It reads the capture and
the light model (a calibration or an illumination file, or lights embedded in the capture by
an importer), solves normals for every contact instance with the chosen solver, integrates
heights, stores both results in the stage store (keyed by parameters and input content, so a
repeated call is a cache hit), copies them to the output folder and writes a normal-map PNG,
a colour-mapped depth PNG and a PLY point cloud per instance.

Where the lights come from (first that applies):

- ``calibration``: ``light_field (P, C, H, W, 3)`` (with optional ``flat_field (P, C, H, W)``
  by which observations are divided first), ``light_vectors (P, C, 3)`` (far field) and
  ``models/lut/*`` (the lookup table);
- ``illumination``: ``light_matrices (P, 3, H, W, 3)``, or ``V (L, H, W, 3)`` combined with
  the capture's ``drive``, ``brightness`` and ``exposure`` (and ``gains (L,)`` or ``(L, 3)``
  if the file has them) by :func:`sim.illumination_model.light_matrices`;
- the capture itself: ``lights/light_vectors (P, C, 3)`` (written by the DiLiGenT importer).

Solvers: ``lstsq`` (far field; given only per-pixel lights it uses the light field at the
image centre, which is what a far-field calibration would measure there), ``nearfield``
(per-pixel lights required), ``robust`` (either; shadows and highlights modelled,
:func:`pipeline.normals.solve_robust_irls`), ``cauchy`` (the earlier robust solver: trimmed
start and Cauchy IRLS, :func:`pipeline.normals.solve_robust`); both robust solvers exclude
values within 1% of full scale of the dark level and saturated raw values; ``lut`` (one RGB
pattern).

Where to solve: the capture's ``mask`` dataset (an object's silhouette, e.g. DiLiGenT's), or a
user's ``mask=`` (a PNG/NPY file or an array), which replaces it. Only those pixels are read
out of the frames, solved and integrated (rectangular integrators on the mask's bounding
box); every pixel outside is invalid in the outputs (:mod:`pipeline.normals.masking`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import UserError

__all__ = ["LightSource", "ReconstructResult", "load_lights", "solve_capture", "normals_record", "depth_record",
           "reconstruct", "NORMALS_VERSION", "DEPTH_VERSION"]

NORMALS_VERSION = 2  # 2: only the capture's (or the user's) mask is solved
DEPTH_VERSION = 2  # 2: rectangular integrators on the mask's bounding box
SOLVERS = ("lstsq", "nearfield", "robust", "cauchy", "lut")


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
    table : object, optional
        A lookup table with ``lookup(images (N, H, W, 3)) -> (gradients, valid)``.
    source : str
        Where the lights came from (for the record's attributes).
    key : str
        Content key of the light file (enters the stage key).
    """

    far: np.ndarray | None = None
    field: np.ndarray | None = None
    flat_field: np.ndarray | None = None
    table: Any = None
    source: str = ""
    key: str = ""


@dataclass
class ReconstructResult:
    """What :func:`reconstruct` produced.

    ``summary`` has the CLI's JSON keys: ``solver``, ``integrator``, ``seconds``,
    ``valid_fraction`` and, when the capture has ground truth, ``normal_mean_error_deg`` and
    ``depth_rmse_mm`` (means over contact instances); plus ``cached`` and ``outputs``.
    """

    normals: Any
    depth: Any
    summary: dict[str, Any]
    files: list[Path] = field(default_factory=list)


def _record_key(rec) -> str:
    """Stage key of a record read from the store, else the content hash of its file."""
    key = rec.provenance.get("iristac_key") if rec.provenance else None
    if key:
        return str(key)
    if rec.path is None:  # an in-memory record: hash its content
        from pipeline.hashing import digest

        return "memory:" + digest({"schema": rec.schema, "data": rec.data, "meta": rec.meta})
    from pipeline.orchestrate import file_input_key

    return file_input_key(rec.path)


def _read(path_or_record, schema: str):
    from pipeline.store import Record, read_record

    if isinstance(path_or_record, Record):
        if path_or_record.schema != schema:
            raise UserError(f"expected a {schema!r} record, got {path_or_record.schema!r}")
        return path_or_record
    p = Path(path_or_record)
    if not p.exists():
        raise UserError(f"{p}: {schema} file not found")
    return read_record(p, schema=schema)


def _check_shape(arr, want: tuple, path, name: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.shape != want:
        raise UserError(f"{path}: dataset {name!r} has shape {a.shape}, expected {want} to match the capture")
    return a


def load_lights(capture, calibration=None, illumination=None) -> LightSource:
    """Resolve the light model for ``capture`` (Records; see the module docstring)."""
    frames = capture.data["frames"]
    _, P, H, W, C = frames.shape
    if calibration is not None and illumination is not None:
        raise UserError("give either a calibration or an illumination file, not both")
    if calibration is not None:
        d, path = calibration.data, calibration.path
        src = LightSource(source=f"calibration:{Path(path).name if path else 'memory'}", key=_record_key(calibration))
        if "light_field" in d:
            src.field = _check_shape(d["light_field"], (P, C, H, W, 3), path, "light_field")
            if "flat_field" in d:
                src.flat_field = _check_shape(d["flat_field"], (P, C, H, W), path, "flat_field")
        if "light_vectors" in d:
            src.far = _check_shape(d["light_vectors"], (P, C, 3), path, "light_vectors")
        lut = {k.split("/", 2)[2]: v for k, v in d.items() if k.startswith("models/lut/")}
        if lut:
            try:
                from calibration.models.lut import LookupTable
            except ImportError:  # the calibration package without a LUT
                LookupTable = None
            if LookupTable is not None:
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
                          key=_record_key(illumination))
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


def _observations(frames_k: np.ndarray) -> np.ndarray:
    """``(P, H, W, C)`` -> solver observations ``(P*C, H, W)`` (pattern-major, channel-minor)."""
    P, H, W, C = frames_k.shape
    return frames_k.transpose(0, 3, 1, 2).reshape(P * C, H, W)


def solve_capture(frames, lights: LightSource, *, solver: str = "lstsq", reference=None, saturated=None,
                  ratio: bool = False, max_condition: float = 1e3, dark_threshold: float = 0.0,
                  device="cpu", dtype="float32", compile: bool = False) -> list:
    """Normals of every contact instance.

    Parameters
    ----------
    frames : ndarray, shape (K, P, H, W, C)
        Dark-subtracted float frames.
    lights : LightSource
    solver : {"lstsq", "nearfield", "robust", "cauchy", "lut"}
    reference : ndarray, shape (P, H, W, C), optional
        Dark-subtracted no-contact frames (needed for ``ratio``).
    saturated : ndarray, shape (K, P, H, W, C), bool, optional
        Raw values at full scale; the robust solver excludes them.
    ratio : bool
        Divide by the reference first (:func:`pipeline.normals.ratio_to_reference`).
    compile : bool
        ``lstsq`` only: the ``torch.compile``-d far-field solver
        (:class:`pipeline.normals.FarFieldSolver`), for long recordings.

    Returns
    -------
    list of NormalResult
        One per contact instance.
    """
    from pipeline import normals as N

    if solver not in SOLVERS:
        raise UserError(f"--solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
    frames = np.asarray(frames, dtype=np.float32)
    K, P, H, W, C = frames.shape
    if solver == "lut":
        if lights.table is None:
            raise UserError(f"--solver lut needs a calibration with a lookup table (models/lut/*); "
                            f"{lights.source or 'the light source'} has none")
        if P != 1 or C != 3:
            raise UserError(f"--solver lut needs one RGB pattern per frame, the capture has P={P}, C={C}")
        lut = N.LUTSolver(lights.table)
        return [lut.solve(frames[k, 0]) for k in range(K)]
    if solver == "nearfield" and lights.field is None:
        raise UserError(f"--solver nearfield needs per-pixel lights (an illumination file or a calibration "
                        f"with light_field); {lights.source} has only far-field light vectors")
    if lights.field is None and lights.far is None:
        raise UserError(f"--solver {solver} needs light vectors; {lights.source} has only a lookup table")
    groups = np.tile(np.arange(C), P)
    _check_light_count(None if lights.far is None else lights.far.reshape(P * C, 3), P, C,
                       lights.source or "the light source")
    if solver == "lstsq":
        # Far field: the calibrated vectors, else the light field at the image centre.
        far = lights.far if lights.far is not None else lights.field[:, :, H // 2, W // 2, :]
        L = far.reshape(P * C, 3)
    else:
        L = lights.field.reshape(P * C, H, W, 3) if lights.field is not None else lights.far.reshape(P * C, 3)
    flat = None
    if lights.field is not None and lights.flat_field is not None and solver != "lstsq":
        flat = lights.flat_field.reshape(P * C, H, W)
    ref = None if reference is None else _observations(np.asarray(reference, np.float32))
    if ratio and ref is None:
        raise UserError("--ratio needs the capture's reference frames")
    common = dict(groups=groups, max_condition=max_condition, device=device, dtype=dtype)
    prebuilt = None
    if not ratio and solver == "lstsq":
        prebuilt = N.FarFieldSolver(L, compile=compile, **common)
    elif not ratio and solver == "nearfield":
        prebuilt = N.NearFieldSolver(L, **common)
    out = []
    for k in range(K):
        obs = _observations(frames[k])
        if flat is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                obs = np.where(flat > 0, obs / np.where(flat > 0, flat, 1.0), np.nan)
        Lk = L
        if ratio:
            r_ref = ref if flat is None else ref / np.where(flat > 0, flat, 1.0)
            obs, Lk = N.ratio_to_reference(obs, r_ref, L)
        if solver in ("robust", "cauchy"):
            if saturated is not None:
                obs = np.where(_observations(saturated[k]), np.inf, obs)  # excluded as non-finite
            thr = dark_threshold if not ratio else 0.0
            robust = N.solve_robust_irls if solver == "robust" else N.solve_robust
            out.append(robust(obs, Lk, dark_threshold=thr, **common))
        elif prebuilt is not None:
            out.append(prebuilt.solve(obs))
        elif solver == "lstsq":
            out.append(N.FarFieldSolver(Lk, **common).solve(obs))
        else:
            out.append(N.NearFieldSolver(Lk, **common).solve(obs))
    return out


def _stack(results, name: str) -> np.ndarray:
    return np.stack([getattr(r, name) for r in results])


def normals_record(cap, lights: LightSource, *, solver: str = "lstsq", ratio: bool = False,
                   max_condition: float = 1e3, device="cpu", dtype="float32", threads: int | None = 1,
                   compile: bool = False, mask=None):
    """Stage 4 on records: the ``normals`` :class:`~pipeline.store.Record` of a capture (no caching).

    Parameters
    ----------
    cap : Record
        Schema ``capture``: ``frames (K, P, H, W, C)``, optional ``reference (P, H, W, C)``,
        ``dark (H, W, C)`` and ``mask (H, W)``; attributes ``mm_per_px`` and ``bit_depth``.
    lights : LightSource
        From :func:`load_lights`.
    solver, ratio, max_condition, device, dtype, threads, compile
        As in :func:`reconstruct`.
    mask : path or ndarray, shape (H, W), optional
        The pixels to solve, replacing the capture's ``mask`` (:func:`capture_region`). Only
        they are read out of the frames and solved; the others are invalid in the result.

    Returns
    -------
    Record
        Schema ``normals``: ``normals (K, H, W, 3)``, ``albedo``, ``residual``, ``condition``,
        ``mask``, ``count``.
    """
    from pipeline.normals._torch import torch_threads
    from pipeline.normals.masking import PixelMask
    from pipeline.store import Record

    mm_per_px = float(cap.meta["mm_per_px"])
    raw = cap.data["frames"]
    H, W = raw.shape[2:4]
    region = capture_region(cap, mask)
    ref = reference_frames(cap)
    dark = cap.data.get("dark")
    pixels = None
    if region is not None and solver != "lut":  # the table needs whole frames: masked after
        # Gather the region once, from the raw frames (no full-frame float copy), as a
        # (1, M) image; the solvers then see only the region's pixels.
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
    with torch_threads(threads):
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


def reference_frames(cap) -> np.ndarray | None:
    """The capture's no-contact ``reference (P, H, W, C)``, or None when it has none (the
    dataset is absent, or a version-1 file marked ``has_reference = False`` holds zeros)."""
    if "reference" not in cap.data or cap.meta.get("has_reference", True) is False:
        return None
    return cap.data["reference"]


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


def depth_record(n_rec, integrator: str = "dst", region=None):
    """Stage 5 on records: integrate every instance of a ``normals`` record into a ``depth`` record.

    Parameters
    ----------
    n_rec : Record
        Schema ``normals``: ``normals (K, H, W, 3)``, ``mask (K, H, W)``, attribute ``mm_per_px``.
    integrator : {"fc", "dct", "dst", "sparse"}
    region : ndarray, shape (H, W), bool, optional
        The solved region (:func:`capture_region`): ``sparse`` integrates on it, the others on
        its bounding box (:func:`pipeline.depth.integrate`).

    Returns
    -------
    Record
        Schema ``depth``: ``height (K, H, W)`` in mm and ``mask (K, H, W)``.
    """
    from pipeline.depth import INTEGRATORS, integrate
    from pipeline.store import Record

    if integrator not in INTEGRATORS:
        raise UserError(f"--integrator must be one of {', '.join(sorted(INTEGRATORS))}, got {integrator!r}")
    mm_per_px = float(n_rec.meta["mm_per_px"])
    outs = [integrate(n_rec.data["normals"][k], mm_per_px, n_rec.data["mask"][k], method=integrator, region=region)
            for k in range(n_rec.data["normals"].shape[0])]
    data = {"height": np.stack([o.height for o in outs]), "mask": np.stack([o.mask for o in outs])}
    meta = {"integrator": integrator, "mm_per_px": mm_per_px}
    if integrator == "sparse":
        meta["converged"] = bool(all(o.meta["converged"] for o in outs))
    return Record("depth", data, meta)


def reconstruct(capture, *, calibration=None, illumination=None, solver: str = "lstsq", integrator: str = "dst",
                out=None, store=None, ratio: bool = False, max_condition: float = 1e3, device="cpu",
                dtype="float32", threads: int | None = 1, images: bool = True, force: bool = False,
                compile: bool = False, mask=None) -> ReconstructResult:
    """Normals and depth of a capture, through the stage store.

    Parameters
    ----------
    capture : path or Record
        ``capture.h5``.
    calibration, illumination : path or Record, optional
        The light model (at most one; see the module docstring).
    solver : {"lstsq", "nearfield", "robust", "cauchy", "lut"}
    integrator : {"fc", "dct", "dst", "sparse"}
    out : path, optional
        Folder for ``normals.h5``, ``depth.h5`` and, with ``images``, per contact instance
        ``normals_kNNN.png``, ``depth_kNNN.png`` and ``depth_kNNN.ply``.
    store : StageStore or path, optional
        The stage store (default: ``$IRISTAC_CACHE`` or ``./iristac-cache``).
    ratio : bool
        Divide by the no-contact reference first.
    max_condition : float
        Pixels with a worse-conditioned light matrix are masked.
    device, dtype, threads
        Torch device and dtype of the solvers; torch intra-op threads while solving
        (default 1: fastest on a small shared CPU; None leaves torch's setting).
    force : bool
        Recompute even if the store has the results.
    compile : bool
        ``lstsq`` only: solve with the ``torch.compile``-d far-field kernel
        (:mod:`pipeline.normals.fused`): about 4x faster per frame after a few seconds of
        compilation, so worth it for recordings of many frames. Not part of the cache key
        (the results agree with the eager solver to float rounding).
    mask : path or ndarray, shape (H, W), optional
        Reconstruct only these pixels (a ``.png``/``.npy`` file, non-zero inside, or an array),
        instead of the capture's own ``mask`` dataset (or every pixel when it has none).

    Returns
    -------
    ReconstructResult
    """
    from pipeline.depth import INTEGRATORS
    from pipeline.store import StageStore

    if solver not in SOLVERS:
        raise UserError(f"--solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
    if integrator not in INTEGRATORS:
        raise UserError(f"--integrator must be one of {', '.join(sorted(INTEGRATORS))}, got {integrator!r}")
    t0 = time.perf_counter()
    cap = _read(capture, "capture")
    cal = None if calibration is None else _read(calibration, "calibration")
    ill = None if illumination is None else _read(illumination, "illumination")
    lights = load_lights(cap, cal, ill)
    if ratio and reference_frames(cap) is None:
        raise UserError(f"{cap.path}: --ratio needs no-contact reference frames (dataset 'reference'); this "
                        f"capture has none (source {cap.meta.get('source')!r})")
    region = capture_region(cap, mask)
    mm_per_px = float(cap.meta["mm_per_px"])
    cap_key = _record_key(cap)
    store = store if isinstance(store, StageStore) else StageStore(store)
    n_params = {"solver": solver, "ratio": bool(ratio), "max_condition": float(max_condition),
                "dtype": str(dtype), "lights": lights.source.split(":")[0]}
    if mask is not None:  # the capture's own mask is part of its content key already
        from pipeline.hashing import digest

        n_params["mask"] = digest(region)
    n_key = store.key("normals", NORMALS_VERSION, n_params, inputs=[cap_key, lights.key])

    def compute_normals():
        return normals_record(cap, lights, solver=solver, ratio=ratio, max_condition=max_condition,
                              device=device, dtype=dtype, threads=threads, compile=compile, mask=region)

    n_rec, n_cached = store.get_or_compute(n_key, compute_normals, force=force)
    d_key = store.key("depth", DEPTH_VERSION, {"integrator": integrator, "mm_per_px": mm_per_px}, inputs=[n_key])

    def compute_depth():
        return depth_record(n_rec, integrator, region)

    d_rec, d_cached = store.get_or_compute(d_key, compute_depth, force=force)
    seconds = time.perf_counter() - t0
    summary: dict[str, Any] = {"solver": solver, "integrator": integrator, "seconds": round(seconds, 4),
                               "valid_fraction": float(np.asarray(n_rec.data["mask"]).mean()),
                               "cached": bool(n_cached and d_cached)}
    summary.update(_truth_errors(cap, n_rec, d_rec, region))
    files: list[Path] = []
    if out is not None:
        files = _write_outputs(Path(out), n_rec, d_rec, mm_per_px, images)
        summary["outputs"] = [str(f) for f in files]
    return ReconstructResult(normals=n_rec, depth=d_rec, summary=summary, files=files)


def _truth_errors(cap, n_rec, d_rec, region=None) -> dict:
    """Mean normal error (deg) and depth RMSE (mm) against the capture's truth, if any, over
    ``region`` (the solved mask; None: every pixel)."""
    from pipeline.evaluate import normal_error_stats

    out: dict[str, float] = {}
    if "truth/normals" in cap.data:
        gt = cap.data["truth/normals"]
        errs = []
        for k in range(gt.shape[0]):
            m = np.linalg.norm(gt[k], axis=-1) > 0
            if region is not None:
                m &= np.asarray(region, bool)
            errs.append(normal_error_stats(n_rec.data["normals"][k], gt[k], m)["mean_deg"])
        out["normal_mean_error_deg"] = float(np.mean(errs))
    if "truth/height" in cap.data:
        diff = d_rec.data["height"].astype(np.float64) - cap.data["truth/height"]
        if region is not None:
            diff = diff[:, np.asarray(region, bool)]
        out["depth_rmse_mm"] = float(np.sqrt(np.mean(diff ** 2)))
    return out


def _write_outputs(out: Path, n_rec, d_rec, mm_per_px: float, images: bool) -> list[Path]:
    from pipeline.outputs import normal_map_rgb, write_depth_png, write_normal_png, write_ply
    from pipeline.store import Record, write_record

    out.mkdir(parents=True, exist_ok=True)
    files = [write_record(out / "normals.h5", Record("normals", n_rec.data, n_rec.meta)),
             write_record(out / "depth.h5", Record("depth", d_rec.data, d_rec.meta))]
    if images:
        for k in range(n_rec.data["normals"].shape[0]):
            n, nm = n_rec.data["normals"][k], n_rec.data["mask"][k]
            h, hm = d_rec.data["height"][k], d_rec.data["mask"][k]
            files.append(write_normal_png(out / f"normals_k{k:03d}.png", n, nm))
            files.append(write_depth_png(out / f"depth_k{k:03d}.png", h, hm))
            files.append(write_ply(out / f"depth_k{k:03d}.ply", h, mm_per_px, hm, colors=normal_map_rgb(n, nm)))
    return files
