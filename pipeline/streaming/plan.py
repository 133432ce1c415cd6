"""A streamed reconstruction planned: the keys of its results, and which of them the store has."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError
from pipeline.frame_pipeline.outputs import OutputSpec
from pipeline.streaming.inputs import colour_matched_record, load_light_record, read_capture
from pipeline.streaming.job import CHUNK_BYTES, CONTACT_SPEC, VERIFY_BYTES, StreamJob

__all__ = ["plan_stream", "colour_gain_for"]


def plan_stream(capture, *, calibration=None, illumination=None, solver: str = "lstsq", integrator: str = "dst",
                store=None, ratio: bool = False, max_condition: float = 1e3, device="cpu", dtype="float32",
                compile: bool = False, mask=None, markers=None, drift: str = "auto", outputs: OutputSpec | None = None,
                force: bool = False, heal: bool = True, video: dict | None = None, match_colours: bool = False
                ) -> tuple[StreamJob, Any, Any]:
    """``(job, capture record, lights)``: the keys of the results, and which of them the store has
    (see the module docstring; arguments as :func:`pipeline.workflows.reconstruct.reconstruct`; ``video``:
    ``reference`` and ``mm_per_px`` of a video file, :func:`video_options`). With ``match_colours``
    the job's ``options["colour_gain"]`` brings the capture's colours to the light model's
    (:func:`colour_gain_for`) and the record's reference is already matched
    (:func:`pipeline.streaming.inputs.colour_matched_record`); the frames are, a chunk at a time,
    as they are read."""
    from pipeline.base.registry import INTEGRATORS, SOLVERS
    from pipeline.base.store import StageStore
    from pipeline.capture.video_frames import video_options
    from pipeline.normals.lights import check_lights
    from pipeline.solving.light_files import capture_lights
    from pipeline.solving.regions import capture_region, marker_mask, reference_frames
    from pipeline.stages import capture as capture_stage
    from pipeline.stages import depth as depth_stage
    from pipeline.stages import normals as normals_stage

    SOLVERS.check(solver)
    INTEGRATORS.check(integrator)
    outputs = outputs or OutputSpec()
    cal = load_light_record(calibration, "calibration")
    ill = load_light_record(illumination, "illumination")
    video = video_options(capture, video, cal, ill)
    cap = read_capture(capture, video)
    lights = capture_lights(cap, cal, ill)
    check_lights(solver, lights, cap.data["frames"].shape[1], cap.data["frames"].shape[-1])
    if ratio and reference_frames(cap) is None:
        raise UserError(f"{cap.path}: --ratio needs no-contact reference frames (dataset 'reference'); this "
                        f"capture has none (source {cap.meta.get('source')!r})")
    gain = colour_gain_for(cap, lights, solver) if match_colours else None
    source, cap = cap, colour_matched_record(cap, gain)  # the capture's identity is its file's, not the match's
    region = capture_region(cap, mask)
    marks = marker_mask(cap, markers, lights)
    user_region = None if mask is None else region
    store = store if isinstance(store, StageStore) else StageStore(store)
    cap_key = capture_stage.capture_key(store, source)
    n_key = normals_stage.SPEC.key(store, normals_stage.key_params(
        lights, solver=solver, ratio=ratio, max_condition=max_condition, dtype=dtype, mask=user_region,
        markers=marks, drift=drift, outputs=outputs, colour_gain=gain), [cap_key, lights.key])
    mm = float(cap.meta["mm_per_px"])
    d_key = depth_stage.SPEC.key(store, depth_stage.params({"integrator": integrator, "mm_per_px": mm}), [n_key])
    keys = {"normals": n_key, "depth": d_key}
    if outputs.contact:
        keys["contact"] = CONTACT_SPEC.key(store, {}, [d_key, cap_key])
    entries = {}
    for name, key in keys.items():
        # Entries up to VERIFY_BYTES are read whole (their checksums verified, a bad one healed);
        # larger ones (a long recording's, written unfiltered) by their structure.
        path = store.path_for(key)
        load = path.is_file() and path.stat().st_size <= VERIFY_BYTES
        done = not force and store.get(key, recompute_bad=heal, load=load) is not None
        # ``force``: rewritten even though the entry is there (the old file stays until the new one replaces it).
        entries[name] = {"key": key, "path": str(store.path_for(key)), "done": done, "force": bool(force)}
    K, P, H, W, C = cap.data["frames"].shape
    frame_bytes = P * H * W * C * np.dtype(cap.data["frames"].dtype).itemsize + 32 * H * W  # frames, results
    job = StreamJob(capture=str(Path(cap.path).resolve()) if cap.path else "",
                    light_files={"calibration": None if cal is None else str(cal.path),
                                 "illumination": None if ill is None else str(ill.path)},
                    options={"solver": solver, "integrator": integrator, "ratio": bool(ratio),
                             "max_condition": float(max_condition), "device": str(device), "dtype": str(dtype),
                             "compile": bool(compile), "drift": drift, "colour_gain": gain},
                    outputs=outputs, region=region, markers=marks, entries=entries, frames=int(K), shape=(H, W),
                    mm_per_px=mm, user_region=mask is not None,
                    chunk=int(min(256, max(4, CHUNK_BYTES // frame_bytes))), video=video)
    return job, cap, lights


def colour_gain_for(cap, lights, solver: str) -> tuple[float, ...]:
    """One gain per channel that brings the capture's colours to those of the unit the light model
    was calibrated on: :func:`pipeline.capture.shipped.colour_gain` of the capture's no-contact
    frame against the reference ``solver``'s model stores (another unit's LEDs have other
    colours; a per-channel gain from the no-contact frames alone undoes most of it). Rounded to
    six digits: it enters the normals' key."""
    from pipeline.capture.shipped import colour_gain
    from pipeline.solving.regions import reference_frames

    ref, stored = reference_frames(cap), lights.stored_reference(solver)
    if ref is None:
        raise UserError(f"{cap.path or 'capture'}: matching its colours to the light model's needs its no-contact "
                        "reference (dataset 'reference'); it has none")
    if stored is None:
        raise UserError(f"{lights.source}: matching a capture's colours to it needs the no-contact reference "
                        f"solver {solver!r}'s model stores (the calibration's lut or mlp); it has none")
    return tuple(round(float(g), 6) for g in colour_gain(ref, stored))
