"""Stage 1, synthesize: ray-trace a scene into the per-pixel illumination model.

For a scene, LED gains and a set of lighting patterns, trace every LED onto the camera's
pixel grid (on the gel plane) and produce :class:`sim.illumination_model.IlluminationModel`:
per-LED vector irradiance ``V`` of shape (L, H, W, 3) in the reconstruction frame, per unit
LED drive, plus per-pattern-channel light matrices (P, 3, H, W, 3) when patterns are given.
The result is ``illumination.h5`` (schema ``illumination``); the synthesize stage
(:mod:`pipeline.stages.synthesize`) caches it in the stage store, keyed over the scene, the
grid, the tracing parameters, the patterns and the gains.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.frames import optical_to_recon
from sim.illumination_model import IlluminationModel, light_matrices
from sim.optics import instrument
from sim.optics.grid import PixelGrid
from sim.optics.multisource import METHODS, trace_all
from sim.scene import Scene, load_scene

__all__ = ["synthesize", "synthesize_record", "check_inputs", "model_from_record", "load_illumination",
           "save_illumination", "default_illumination"]


def _as_scene(scene) -> Scene:
    return scene if isinstance(scene, Scene) else load_scene(scene)


def check_inputs(scene: Scene, shape, mm_per_px, drive, brightness, gains):
    """UserError naming the argument when the grid, patterns or gains do not fit the scene."""
    if len(tuple(shape)) != 2 or min(int(s) for s in shape) < 1:
        raise UserError(f"synthesize: shape must be (H, W) with H, W >= 1, got {tuple(shape)}")
    if not (isinstance(mm_per_px, (int, float)) and math.isfinite(mm_per_px) and mm_per_px > 0):
        raise UserError(f"synthesize: mm_per_px must be a positive number, got {mm_per_px!r}")
    L = scene.leds.count
    if drive is not None:
        drive = np.asarray(drive, dtype=np.float64)
        if drive.ndim != 3 or drive.shape[1:] != (L, 3):
            raise UserError(f"synthesize: drive must have shape (P, {L}, 3), got {drive.shape}")
        if brightness is not None and np.shape(brightness) != (drive.shape[0],):
            raise UserError(f"synthesize: brightness must have shape ({drive.shape[0]},), got {np.shape(brightness)}")
    if gains is not None and np.shape(gains) not in ((L,), (L, 3)):
        raise UserError(f"synthesize: gains must have shape ({L},) or ({L}, 3), got {np.shape(gains)}")


def synthesize(scene, shape, mm_per_px: float, *, drive=None, brightness=None, gains=None, exposure: float = 1.0,
               rays: int | None = None, sampler: str | None = None, seed: int | None = None, method: str = "hits",
               device="cpu", dtype=None, engine: str | None = None) -> IlluminationModel:
    """Trace ``scene`` onto a camera pixel grid and return its illumination model.

    Parameters
    ----------
    scene : Scene, or a shipped scene name or YAML path
    shape : (H, W)
        Camera image size; the optical axis passes through the image centre.
    mm_per_px : float
        Pixel pitch on the gel (orthographic camera, :mod:`pipeline.base.frames`).
    drive : ndarray, shape (P, L, 3), optional
        Lighting patterns (RGB drive per LED). When given the result's ``meta`` holds
        ``light_matrices`` (P, 3, H, W, 3) and the illumination file has them as a dataset.
    brightness : ndarray, shape (P,), optional
    gains : ndarray, shape (L,) or (L, 3), optional
        Calibrated per-LED (per-channel) brightness ``sigma_i``; they scale the light
        matrices, never ``V`` (which stays per unit drive).
    exposure : float
        Camera exposure ``mu`` of the light matrices.
    rays, sampler, seed : optional
        Rays per traced LED and sampler; default to the scene's ``trace`` section.
    method : {"hits", "image", "trace"}
        How every LED is obtained (:mod:`sim.optics.multisource`).
    device, dtype :
        Device and float type (float32 default, or float64) of the trace (V is returned as float32).
    engine : {"kernel", "torch"}, optional
        The compiled kernel (default) or the eager torch reference (:mod:`sim.optics.engine`).

    Returns
    -------
    IlluminationModel
        ``V`` (L, H, W, 3) reconstruction frame; ``V_depth`` (D, L, H, W, 3) when the scene
        lists ``depth_field``; ``meta["light_matrices"]`` when ``drive`` is given.

    Examples
    --------
    >>> m = synthesize("default", (6, 8), 2.0, rays=4096)
    >>> m.V.shape, bool(m.V[..., 2].mean() > 0)
    ((24, 6, 8, 3), True)
    """
    scene = _as_scene(scene)
    if method not in METHODS:
        raise UserError(f"synthesize: method must be one of {METHODS}, got {method!r}")
    check_inputs(scene, shape, mm_per_px, drive, brightness, gains)
    shape = (int(shape[0]), int(shape[1]))
    kw = dict(drive=drive, brightness=brightness, gains=gains, exposure=exposure, rays=rays, sampler=sampler,
              seed=seed, method=method, device=device, dtype=dtype, engine=engine)
    return model_from_record(synthesize_record(scene, shape, mm_per_px, **kw))


def synthesize_record(scene, shape, mm_per_px: float, *, drive=None, brightness=None, gains=None,
                      exposure: float = 1.0, rays=None, sampler=None, seed=None, method="hits", device="cpu",
                      dtype=None, engine=None):
    """Compute the ``illumination`` :class:`pipeline.base.store.Record` (no caching)."""
    from pipeline.base.store import Record

    scene = _as_scene(scene)
    grid = PixelGrid.camera(shape, mm_per_px, scene.plane.z)
    depth = scene.has("depth_field")
    heights = tuple(sorted({0.0, *scene.depth_heights})) if depth else (0.0,)
    indices = (None,)
    if scene.has("dispersion"):
        instrument.count("dispersion")
        indices = scene.lens.channel_indices()
    fields, traces = [], []
    for n_ch in indices:
        res = trace_all(scene, grid, method=method, heights=heights, rays=rays, sampler=sampler, seed=seed,
                        device=device, dtype=dtype, engine=engine, refractive_index=n_ch)
        fields.append(optical_to_recon(res.V.astype(np.float64)))  # (D, L, H, W, 3)
        traces.extend(res.traces)
    Vc = np.stack(fields)  # (C, D, L, H, W, 3), C = 3 with dispersion else 1
    Vall = Vc.mean(axis=0)
    i0 = heights.index(0.0)
    data = {"V": Vall[i0].astype(np.float32), "led_positions": scene.leds.geometry()[0].astype(np.float32)}
    if depth:
        data["depth_heights"] = np.asarray(heights, dtype=np.float32)
        data["V_depth"] = Vall.astype(np.float32)
    if len(indices) > 1:
        data["V_channels"] = Vc[:, i0].astype(np.float32)  # (3, L, H, W, 3): V seen by each camera channel
    if drive is not None:
        drive = np.asarray(drive, dtype=np.float32)
        data["drive"] = drive
        if brightness is not None:
            data["brightness"] = np.asarray(brightness, dtype=np.float32)
        if gains is not None:
            data["gains"] = np.asarray(gains, dtype=np.float32)
        if len(indices) > 1:
            # Camera channel j sees the field traced with channel j's refractive index.
            lm = np.stack([light_matrices(Vc[j, i0], drive, brightness, exposure, gains)[:, j] for j in range(3)], 1)
        else:
            lm = light_matrices(Vall[i0], drive, brightness, exposure, gains)
        data["light_matrices"] = lm.astype(np.float32)
    meta = {"mm_per_px": float(mm_per_px), "gel_z": float(scene.plane.z), "scene": scene.name,
            "method": method, "rays_per_source": int(traces[0].rays), "sampler": sampler or scene.trace.sampler,
            "effects": sorted(e for e in scene.effects if scene.has(e)), "exposure": float(exposure),
            "fraction_on_grid": float(np.mean(res.fraction_on_grid)),
            "energy_residual": float(max(abs(t.energy.residual) for t in traces))}
    return Record(schema="illumination", data=data, meta=meta)


def model_from_record(rec) -> IlluminationModel:
    """Build the :class:`IlluminationModel` of an ``illumination`` record."""
    d, m = rec.data, dict(rec.meta)
    meta = {k: v for k, v in m.items() if k not in ("mm_per_px", "gel_z")}
    for name in ("light_matrices", "drive", "brightness", "gains", "V_channels"):
        if name in d:
            meta[name] = np.asarray(d[name])
    return IlluminationModel(V=np.asarray(d["V"], dtype=np.float32), mm_per_px=float(m["mm_per_px"]),
                             led_positions=np.asarray(d["led_positions"], dtype=np.float64), gel_z=float(m["gel_z"]),
                             depth_heights=None if "depth_heights" not in d else np.asarray(d["depth_heights"]),
                             V_depth=None if "V_depth" not in d else np.asarray(d["V_depth"], dtype=np.float32),
                             meta=meta)


def load_illumination(path) -> IlluminationModel:
    """Read ``illumination.h5`` (validated against the schema) into an :class:`IlluminationModel`."""
    from pipeline.base.store import read_record

    return model_from_record(read_record(Path(path), schema="illumination"))


def save_illumination(model: IlluminationModel, path) -> Path:
    """Write an :class:`IlluminationModel` as a standalone ``illumination.h5`` (atomic, validated)."""
    from pipeline.base.store import Record, write_record

    data = {"V": np.asarray(model.V, dtype=np.float32),
            "led_positions": np.asarray(model.led_positions, dtype=np.float32)}
    if model.V_depth is not None:
        data["V_depth"] = np.asarray(model.V_depth, dtype=np.float32)
        data["depth_heights"] = np.asarray(model.depth_heights, dtype=np.float32)
    meta = {"mm_per_px": float(model.mm_per_px), "gel_z": float(model.gel_z)}
    for k, v in model.meta.items():
        if isinstance(v, np.ndarray):
            data[k] = v.astype(np.float32)
        else:
            meta[k] = v
    return write_record(Path(path), Record(schema="illumination", data=data, meta=meta))


def default_illumination(shape=(60, 80), mm_per_px: float = 0.5, rays: int = 250_000, scene="default",
                         device="cpu") -> IlluminationModel:
    """A quick traced illumination model of the default scene for tests and demos.

    One LED is traced with ``rays`` rays on the paper's deterministic grid and every LED is
    obtained by hit rotation (exact), so 24 LEDs cost about one trace.

    Examples
    --------
    >>> m = default_illumination((12, 16), 2.0, rays=10_000)
    >>> m.V.shape, m.num_leds
    ((24, 12, 16, 3), 24)
    """
    return synthesize(scene, shape, mm_per_px, rays=rays, sampler="grid", method="hits", device=device)
