"""The photometric-stereo section of ``iristac bench reconstruct``: objects under 96 far-field lights.

Test data with what real objects have (:mod:`sim.ps_objects`): a specular sphere, a bumpy
object (cast shadows, varying colour) and a Lambertian sphere, each of 15.8k pixels (radius
71 px) in a 612 x 512 black frame under 96 DiLiGenT-like lights (8 x 12 grid within 45
degrees of the view axis), Cook-Torrance highlights (F0 0.04, roughness 0.3), shot and read
noise, 16-bit quantisation and saturation. Every solver runs on the object's mask (gathered
from the uint16 frames, solved, scattered back into the full frame: what ``reconstruct``
does) and, for comparison, on the mask's bounding box cropped out of the frames (cropping,
solving every box pixel and pasting the result into the full frame timed: the same product).
Times are the best of ``--repeats`` runs, solvers interleaved, wall and process CPU time
(one torch thread: what the solve costs when it has a core; the masked-vs-box comparison uses
it, since on the shared machine wall time includes waiting for a core); errors are mean
angles to the rendered truth over the mask. The end-to-end row times ``pipeline.workflows.reconstruct.reconstruct`` of
the specular sphere written as ``capture.h5``: read, solve, integrate (DST on the bounding box),
write ``normals.h5`` and ``depth.h5``.

Targets (this 2-core CPU, one torch thread): lstsq <= 50 ms and robust <= 1 s on the
masked 15.8k-pixel object, robust error <= 1.0 deg on the specular sphere, and no solver
slower on the masked object than on its bounding box.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["measure_ps", "ps_rows", "format_ps", "TARGETS"]

#: The photometric-stereo targets: seconds per solve on the masked object, error of robust (deg).
TARGETS = {"lstsq_seconds": 0.050, "robust_seconds": 1.0, "robust_error_deg": 1.0}
SOLVERS = ("lstsq", "robust", "cauchy", "trimmed")
OBJECTS = {  # name: (object, specular F0)
    "specular sphere": ("sphere", 0.04),
    "bumpy (cast shadows)": ("bumpy", 0.04),
    "Lambertian sphere": ("sphere", 0.0),
}


def _solve_fn(name: str, L: np.ndarray, groups: np.ndarray, device: str):
    """``f(frames (P, H, W, C) uint16, mask or None) -> NormalResult`` for a solver name."""
    from pipeline.normals import FarFieldSolver, PixelMask, solve_cauchy, solve_robust_irls

    if name == "lstsq":
        far = FarFieldSolver(L, groups=groups, device=device)
        return lambda frames, mask: far.solve_frames(frames, mask=mask)
    kw = dict(groups=groups, dark_threshold=0.01 * 65535, saturation=65535.0, device=device)
    solve = {"robust": solve_robust_irls, "cauchy": solve_cauchy,
             "trimmed": lambda o, l, **k: solve_cauchy(o, l, method="trim", **k)}[name]

    def run(frames, mask):
        P, H, W, C = frames.shape
        if mask is None:
            obs = np.ascontiguousarray(frames.transpose(0, 3, 1, 2)).reshape(P * C, H, W)
            return solve(obs, L, **kw)
        pm = PixelMask(mask, (H, W))  # as reconstruct does: gather from the raw frames once
        return pm.scatter(solve(pm.gather_frames(frames), L, **kw))

    return run


def measure_ps(radius_px: float = 71.0, lights=(8, 12), frame=(512, 612), repeats: int = 5, device: str = "cpu",
               solvers=SOLVERS) -> dict:
    """Render the objects, time and score every solver masked and on the bounding box, and
    time ``reconstruct`` end to end. Returns a dict (see :func:`format_ps`)."""
    from pipeline.normals import PixelMask
    from pipeline.results.evaluate import normal_error_stats
    from sim.ps_objects import bumpy_object, dome_lights, render_ps_capture, sphere_object

    size = int(2 * np.ceil(radius_px) + 18)
    d, e = dome_lights(int(lights[0]), int(lights[1]))
    out = {"radius_px": radius_px, "lights": int(len(d)), "frame": list(frame), "repeats": repeats, "objects": {}}
    first = None
    for label, (kind, spec) in OBJECTS.items():
        obj = (sphere_object if kind == "sphere" else bumpy_object)((size, size), radius_px)
        t0 = time.perf_counter()
        rec = render_ps_capture(obj, d, e, specular=spec, roughness=0.3, frame_shape=frame, seed=1)
        render_s = time.perf_counter() - t0
        if first is None:
            first = rec
        frames, mask, truth = rec.data["frames"][0], rec.data["mask"], rec.data["truth/normals"][0]
        P = frames.shape[0]
        L = rec.data["lights/light_vectors"].reshape(P * 3, 3)
        groups = np.tile(np.arange(3), P)
        rows, cols = PixelMask(mask, mask.shape).bbox()
        crop = np.ascontiguousarray(frames[:, rows, cols])  # for the shapes; each timed run crops again
        box = np.zeros(mask.shape, bool)
        box[rows, cols] = True
        box_pixels = PixelMask(box, mask.shape)  # pastes a box result into the full frame
        fns = {s: _solve_fn(s, L, groups, device) for s in solvers}
        best = {s: {k: np.inf for k in ("masked", "masked_cpu", "bbox", "bbox_cpu")} for s in solvers}
        results = {}

        def timed(s, key, fn):
            t, c = time.perf_counter(), time.process_time()
            out = fn()
            best[s][key] = min(best[s][key], time.perf_counter() - t)
            best[s][key + "_cpu"] = min(best[s][key + "_cpu"], time.process_time() - c)
            return out

        for _ in range(max(1, repeats)):
            for s, f in fns.items():  # interleaved: a burst of load elsewhere hits every solver alike
                results[s] = timed(s, "masked", lambda: f(frames, mask))
                # Crop, solve, paste into the full frame: the same product as the masked solve.
                timed(s, "bbox", lambda: _paste(f(np.ascontiguousarray(frames[:, rows, cols]), None), box_pixels))
        out["objects"][label] = {
            "pixels": int(mask.sum()), "bbox_pixels": int(crop.shape[1] * crop.shape[2]), "render_seconds": render_s,
            "solvers": {s: {"mean_deg": normal_error_stats(results[s].normals, truth, mask)["mean_deg"],
                            "valid": float(results[s].mask[mask].mean()), "seconds": best[s]["masked"],
                            "cpu_seconds": best[s]["masked_cpu"], "bbox_seconds": best[s]["bbox"],
                            "bbox_cpu_seconds": best[s]["bbox_cpu"]} for s in solvers}}
    out["reconstruct"] = _end_to_end(first, device)
    return out


def _paste(res, pixels):
    """A bounding-box result ``(h, w, ...)`` as the full frame's (``pixels``: the box's PixelMask)."""
    from pipeline.normals import NormalResult

    flat = {k: getattr(res, k).reshape((1, -1) + getattr(res, k).shape[2:])
            for k in ("normals", "albedo", "residual", "condition", "mask", "count")}
    return pixels.scatter(NormalResult(**flat, meta=res.meta))


def _end_to_end(rec, device: str) -> dict:
    """``reconstruct`` of the specular sphere from its file, per solver (fresh store: no cache)."""
    from pipeline.base.capture import write_capture
    from pipeline.workflows.reconstruct import reconstruct

    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = write_capture(Path(tmp) / "capture.h5", rec)
        for solver in ("lstsq", "robust"):
            t = time.perf_counter()
            r = reconstruct(path, solver=solver, integrator="dst", out=Path(tmp) / solver, store=Path(tmp) / "cache",
                            images=False, device=device)
            res[solver] = {"seconds": time.perf_counter() - t, "mean_deg": r.summary["normal_mean_error_deg"]}
    return res


def ps_rows(ps: dict) -> list[dict]:
    """Rows for ``iristac bench all``: error and time per object and solver (masked and box)."""
    rows = []
    for label, o in ps["objects"].items():
        for s, v in o["solvers"].items():
            knob = f"PS solver, {label} ({o['pixels'] / 1000:.1f}k px, {ps['lights']} lights)"
            rows.append({"knob": knob, "setting": f"{s} (masked)", "error": v["mean_deg"], "error_unit": "deg",
                         "seconds": v["seconds"]})
            rows.append({"knob": knob, "setting": f"{s} (bounding box)", "error": None, "seconds": v["bbox_seconds"]})
    for s, v in ps["reconstruct"].items():
        rows.append({"knob": "reconstruct capture.h5 (specular sphere)", "setting": f"{s} + dst", "error": v["mean_deg"],
                     "error_unit": "deg", "seconds": v["seconds"]})
    return rows


def targets(ps: dict) -> list[tuple[str, bool]]:
    """Each of :data:`TARGETS` with whether it is met."""
    spec = ps["objects"]["specular sphere"]["solvers"]
    out = []
    if "lstsq" in spec:
        out.append((f"lstsq <= {TARGETS['lstsq_seconds'] * 1e3:.0f} ms on the masked specular sphere: "
                    f"{spec['lstsq']['seconds'] * 1e3:.1f} ms", spec["lstsq"]["seconds"] <= TARGETS["lstsq_seconds"]))
    if "robust" in spec:
        out.append((f"robust <= {TARGETS['robust_seconds']:.0f} s on the masked specular sphere: "
                    f"{spec['robust']['seconds']:.3f} s", spec["robust"]["seconds"] <= TARGETS["robust_seconds"]))
        ls = f" (lstsq {spec['lstsq']['mean_deg']:.2f} deg)" if "lstsq" in spec else ""
        out.append((f"robust error <= {TARGETS['robust_error_deg']:.1f} deg on the specular sphere: "
                    f"{spec['robust']['mean_deg']:.3f} deg{ls}", spec["robust"]["mean_deg"] <= TARGETS["robust_error_deg"]))
    for label, o in ps["objects"].items():
        # Process CPU time (one torch thread): on this shared machine wall time includes
        # waiting for a core, which differs between two runs milliseconds apart.
        slower = [s for s, v in o["solvers"].items() if v["cpu_seconds"] > v["bbox_cpu_seconds"]]
        out.append((f"no solver slower masked than on the bounding box, in CPU time ({label})"
                    + (f": slower: {', '.join(slower)}" if slower else ""), not slower))
    return out


def format_ps(ps: dict) -> str:
    """The section's table and its targets, met / NOT met."""
    lines = [f"\n== photometric stereo: {ps['lights']} far-field lights within 45 deg, objects of radius "
             f"{ps['radius_px']:g} px in a {ps['frame'][1]}x{ps['frame'][0]} frame, 16-bit, noise, "
             f"best of {ps['repeats']} (solvers interleaved)"]
    lines.append(f"{'object':<24}{'solver':<10}{'mean err deg':>13}{'valid':>7}{'masked ms':>11}{'cpu ms':>9}"
                 f"{'bbox ms':>10}{'cpu ms':>9}")
    for label, o in ps["objects"].items():
        for s, v in o["solvers"].items():
            lines.append(f"{label:<24}{s:<10}{v['mean_deg']:13.3f}{v['valid']:7.3f}{v['seconds'] * 1e3:11.1f}"
                         f"{v['cpu_seconds'] * 1e3:9.1f}{v['bbox_seconds'] * 1e3:10.1f}{v['bbox_cpu_seconds'] * 1e3:9.1f}")
        lines.append(f"{'':<24}({o['pixels']} object pixels, bounding box {o['bbox_pixels']}; rendered in "
                     f"{o['render_seconds']:.1f} s)")
    for s, v in ps["reconstruct"].items():
        lines.append(f"reconstruct capture.h5 -> normals.h5 + depth.h5, {s} + dst: {v['seconds']:.2f} s "
                     f"(mean err {v['mean_deg']:.3f} deg)")
    if ps["radius_px"] != 71.0 or ps["lights"] != 96:
        lines.append("(the targets are for a 15.8k-pixel object (radius 71 px) under 96 lights; this run is smaller)")
    for text, ok in targets(ps):
        lines.append(f"target {text}: {'met' if ok else 'NOT met'}")
    return "\n".join(lines)
