"""``iristac bench live``: the live paths, uint8 frames to heights, error and time side by side.

Per solver and image size, the eager reference (the solver ``reconstruct`` runs, then
:func:`pipeline.depth.poisson.poisson_dst`) and the live fast path (precomputed per
calibration, :mod:`pipeline.solving.frame_solvers`, then :class:`pipeline.depth.fast.FastDST`),
on one thread and on every core:

- **near field**: the reconstruct benchmark's scene (a 3 mm ball pressed 0.5 mm, 8 white
  sectors of the bare 24-LED ring x RGB, 8-bit, 1 DN noise; :mod:`pipeline.bench.recon_scene`)
  with its exact per-pixel lights; also the point mode (24 LEDs x RGB = 72 observations) at
  the first size;
- **LUT** and **MLP**: the virtual sensor in trichromatic mode, calibrated as ``iristac live
  --virtual`` does (rendered ball presses through the calibrate stage, cached in the store:
  only the first run pays), on rendered test presses the calibration never saw; as ``live``
  runs them by default, each frame's illumination drift against the reference removed
  (``--drift auto``: a gain and an offset per channel fitted on
  :data:`pipeline.normals.drift.LIVE_SAMPLES` pixels), and again with ``--drift none``
  (rows ``lut (--drift none)``): the difference is what drift removal costs per frame;
- **conv** and **conv-fast**: the convolutional network (:mod:`calibration.models.conv`) and its
  variant on the frame shrunk by 2 the same way; they have no compiled fast path, so their
  "fast" rows run the model's own ``normal_maps`` (torch) per frame. Their calibrations fit for
  a minute or two each (cached in the store: only the first run pays); ``--models`` chooses
  the calibrated models timed.

Errors: mean angular error of the normals against the rendered truth (every pixel), and the
largest deviation of the fast path from the eager one (deg). Targets (on a 2-core
CPU): near field + DST >= 400 fps at 320 x 240 and >= 100 fps at 640 x 480 with an error
within 0.05 deg of the eager near-field solver; LUT and MLP single-frame >= 200 fps at
320 x 240; the neighbourhood model's live variant (conv-fast) >= 60 fps at 320 x 240; judged on
the better of one thread and all cores, both printed.

Start-up: a fresh process imports, precomputes and reconstructs its first frame (Numba's
compiled code cached on disk); the compile itself (an empty cache, once per machine) is
timed separately. ``--device cuda``: the batched torch path (:mod:`pipeline.normals.batched`
normals and :mod:`pipeline.depth.batched` FFT depth on the device, ``--batch`` frames per upload) is timed too.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

from pipeline.bench.live_scaling import FOV_MM, max_deviation_deg, mean_error_deg, measure_device

__all__ = ["add_arguments", "run", "format_table", "TARGETS"]

#: (solver, size) -> frames per second to reach.
TARGETS = {("nearfield", "320x240"): 400.0, ("nearfield", "640x480"): 100.0, ("lut", "320x240"): 200.0,
           ("mlp", "320x240"): 200.0, ("conv-fast", "320x240"): 60.0}
#: The fast near-field path's error may exceed the eager solver's by at most this (deg).
ERROR_MARGIN_DEG = 0.05
#: The calibrated models ``bench live`` times on the virtual sensor (``--models``).
MODEL_SOLVERS = ("lut", "mlp", "conv", "conv-fast")


def add_arguments(parser) -> None:
    parser.add_argument("--sizes", nargs="*", default=None, metavar="WxH",
                        help="image sizes (default 320x240 640x480; --quick: 160x120)")
    parser.add_argument("--repeats", type=int, default=None, help="timing repeats (best kept; default 30)")
    parser.add_argument("--device", default="cpu", help="also time the batched torch path on this device (cuda)")
    parser.add_argument("--batch", type=int, default=256, help="frames per batch of the device path (8 batches are "
                        "timed: 2,048 frames, 3.8 GB of host memory at 320 x 240)")
    parser.add_argument("--cache", default=None, help="stage store for the virtual sensor's calibrations")
    parser.add_argument("--no-startup", action="store_true", help="skip the fresh-process start-up measurements")
    parser.add_argument("--models", nargs="*", default=None, metavar="SOLVER",
                        help="the calibrated models timed on the virtual sensor (default: "
                             + " ".join(MODEL_SOLVERS) + "; their calibrations are cached in --cache)")


def _runs(fn, repeats: int):
    """``(times, result)``: the wall time of each of ``repeats`` runs."""
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return times, out


def _row(solver, size, path, threads, sec, err, dev=None, extra=None):
    r = {"solver": solver, "size": size, "path": path, "threads": threads, "seconds": sec, "fps": 1.0 / sec,
         "error_deg": err, "deviation_deg": dev}
    r.update(extra or {})
    return r


def measure_nearfield(width: int, height: int, repeats: int, patterns: int = 8, label: str = "nearfield",
                      threads_all: int = 2, frame_rows: bool | str = False) -> list[dict]:
    from pipeline.bench.live_scaling import frame_parallel_rows
    from pipeline.bench.recon_scene import render_sphere_scene
    from pipeline.depth.fast import FastDST
    from pipeline.depth.poisson import poisson_dst
    from pipeline.normals.fast import NearFieldFast
    from pipeline.normals.nearfield import NearFieldSolver

    mm = FOV_MM / width
    # 8: white sectors of 3 LEDs; 24: one LED at a time (the point mode).
    s = render_sphere_scene((height, width), mm, radius=3.0, depth=0.5, num_patterns=patterns, noise=1.0, bits=8,
                            seed=0)
    frames = s.frames.astype(np.uint8)
    P = frames.shape[0]
    groups = np.tile(np.arange(3), P)
    obs = frames.transpose(0, 3, 1, 2).reshape(P * 3, height, width)
    size = f"{width}x{height}"
    eager = NearFieldSolver(s.lights_flat(), groups=groups)

    def eager_pipe():
        r = eager.solve(obs)
        return r, poisson_dst(r.normals, mm, r.mask)

    times, (re_, _) = _runs(eager_pipe, max(3, repeats // 5))
    e_eager = mean_error_deg(re_.normals, s.normals)
    rows = [_row(label, size, "eager", 1, min(times), e_eager, extra={"seconds_runs": times})]
    t = time.perf_counter()
    fast = NearFieldFast(s.lights_flat(), groups=groups)
    dst = FastDST((height, width), mm)
    prep = time.perf_counter() - t
    rows += _fast_rows(label, size, lambda th: fast.solve(frames, threads=th), dst, repeats, threads_all,
                       s.normals, re_.normals, re_.mask,
                       {"eager_error_deg": e_eager, "prepare_seconds": prep, "observations": P * 3})
    if frame_rows:  # throughput: frames in parallel (pipeline.frame_pipeline.cpu_batch)
        rows += frame_parallel_rows(label, size, fast, dst, frames, s.normals, threads_all, repeats,
                                    per_frame=frame_rows == "compare")
    return rows


def _fast_rows(label: str, size: str, solve, dst, repeats: int, threads_all: int, truth: np.ndarray,
               eager_normals: np.ndarray, eager_mask: np.ndarray, extra: dict) -> list[dict]:
    """A fast path's rows, one per thread count: ``solve(threads)`` then ``dst`` heights, warmed
    once, best of ``repeats``, its error against ``truth`` and its deviation from the eager normals."""
    rows = []
    for th in (1, threads_all):
        def fast_pipe(th=th):
            r = solve(th)
            return r, dst.integrate(r.normals, r.mask, workers=th)

        fast_pipe()
        times, (rf, _) = _runs(fast_pipe, repeats)
        rows.append(_row(label, size, "fast", th, min(times), mean_error_deg(rf.normals, truth),
                         max_deviation_deg(rf.normals, eager_normals, rf.mask & eager_mask), dict(extra, seconds_runs=times)))
    return rows


def sensor_calibration(store, w: int, h: int, solver: str):
    from pipeline.base.hashing import digest
    from pipeline.live import virtual_calibration
    from sim.render import bare_ring_illumination

    model = bare_ring_illumination((h, w), FOV_MM / w)
    cal = virtual_calibration(store, model, "bare-ring:" + digest(np.asarray(model.V, np.float32)), "trichromatic",
                              solver)
    return model, cal


def measure_model(solver: str, width: int, height: int, repeats: int, store, threads_all: int = 2) -> list[dict]:
    from calibration.stored import calibration_from_record
    from pipeline.base.modes import load_mode
    from pipeline.depth.fast import FastDST
    from pipeline.depth.poisson import poisson_dst
    from pipeline.normals.lights import LightSource
    from pipeline.solving.frame_solvers import frame_solver
    from sim.contacts import contact_surfaces
    from sim.rendered_capture import render_capture

    model, cal = sensor_calibration(store, width, height, solver)
    models, _ = calibration_from_record(cal)
    m = models[solver]
    mm = model.mm_per_px
    presses = contact_surfaces("sphere", (height, width), mm, 2, size_mm=2.0, depth_mm=0.5,
                               spread_mm=0.25 * height * mm, seed=101)
    cap = render_capture(model, load_mode("trichromatic"), presses, noise_dn=1.0, bit_depth=8, seed=77)
    raw = cap.data["frames"][0]  # (1, H, W, 3) uint8, a press the calibration never saw
    dark = cap.data["dark"].astype(np.float32)
    ref = cap.data["reference"].astype(np.float32) - dark
    truth = cap.data["truth/normals"][0]
    size = f"{width}x{height}"

    src = LightSource(models=models, source="bench")
    raw_ref = cap.data["reference"]
    eager = frame_solver(solver, src, shape=(height, width), reference=raw_ref, dark=dark, fast=False)

    def eager_pipe():  # the model's normal_maps, after the same drift removal
        r = eager.solve(raw)
        return r, poisson_dst(r.normals, mm, r.mask)

    times, (er, _) = _runs(eager_pipe, max(2, repeats // 10))
    e_eager = mean_error_deg(er.normals, truth)
    rows = [_row(solver, size, "eager", 1, min(times), e_eager, extra={"seconds_runs": times})]
    dst = FastDST((height, width), mm)
    for drift, label in (("auto", solver), ("none", f"{solver} (--drift none)")):
        t = time.perf_counter()
        fs = frame_solver(solver, src, shape=(height, width), reference=raw_ref, dark=dark, drift=drift)
        prep = time.perf_counter() - t
        base = er if drift == "auto" else m.normal_maps(raw.astype(np.float32)[None] - dark, ref)
        normals, mask = (base.normals, base.mask) if drift == "auto" else (base.normals[0], base.mask[0])
        rows += _fast_rows(label, size, lambda th, fs=fs: fs.solve(raw, threads=th), dst, repeats, threads_all,
                           truth, normals, mask, {"eager_error_deg": e_eager, "prepare_seconds": prep})
    return rows


_STARTUP = r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np
from pipeline.bench.recon_scene import render_sphere_scene
s = render_sphere_scene((240, 320), 0.05, num_patterns=8, noise=1.0, bits=8, seed=0)
frames = s.frames.astype(np.uint8)
t1 = time.perf_counter()
from pipeline.normals.fast import NearFieldFast
from pipeline.depth.fast import FastDST
t2 = time.perf_counter()
fast = NearFieldFast(s.lights_flat(), groups=np.tile(np.arange(3), 8)); dst = FastDST((240, 320), 0.05)
t3 = time.perf_counter()
r = fast.solve(frames); dst.integrate(r.normals, r.mask)
t4 = time.perf_counter()
print(json.dumps({"scene_s": t1 - t0, "import_s": t2 - t1, "precompute_s": t3 - t2, "first_frame_s": t4 - t3,
                  "process_to_first_frame_s": (t4 - t0) - (t1 - t0)}))
"""


def measure_startup() -> dict:
    """A fresh process: import, precompute, first frame (cached compiled code); and the compile
    itself, in a process with an empty Numba cache."""
    import tempfile
    from pathlib import Path

    import pipeline

    out = {}
    repo = str(Path(pipeline.__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=repo + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", _STARTUP], capture_output=True, text=True, env=env, timeout=600)
    out["cached"] = json.loads(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 else {"error": r.stderr[-500:]}
    with tempfile.TemporaryDirectory(prefix="iristac-numba-") as d:
        env2 = dict(env, NUMBA_CACHE_DIR=d)
        r = subprocess.run([sys.executable, "-c", _STARTUP], capture_output=True, text=True, env=env2, timeout=900)
        out["empty_cache"] = (json.loads(r.stdout.strip().splitlines()[-1]) if r.returncode == 0
                              else {"error": r.stderr[-500:]})
    return out


def run(args) -> dict:
    """Measure (see the module docstring); torch and BLAS on one thread each (their spinning
    workers collapse on a shared 2-core machine: the eager solver then took 0.85 s a frame
    instead of 8 ms), the fast paths on ``threads`` of their own."""
    from pipeline.base.threads import limit_threads

    with limit_threads(torch=1, blas=1):
        return _run(args)


def _run(args) -> dict:
    from pipeline.base.store import StageStore

    quick = getattr(args, "quick", False)
    sizes = getattr(args, "sizes", None) or (["160x120"] if quick else ["320x240", "640x480"])
    repeats = getattr(args, "repeats", None) or (5 if quick else 30)
    store = StageStore(getattr(args, "cache", None))
    models = getattr(args, "models", None)
    models = MODEL_SOLVERS if models is None else tuple(models)
    from pipeline.base.errors import UserError
    from pipeline.base.registry import SOLVERS

    calibrated = [n for n in SOLVERS.names() if str(SOLVERS.get(n).info.get("needs", "")).startswith("model:")]
    bad = [m for m in models if m not in calibrated]
    if bad:
        raise UserError(f"bench live --models: {', '.join(bad)} is no calibrated model's solver (expected some of "
                        f"{', '.join(calibrated)})")
    cores = os.cpu_count() or 1
    rows: list[dict] = []
    load = os.getloadavg()
    for spec in sizes:
        w, h = (int(v) for v in spec.lower().split("x"))
        rows += measure_nearfield(w, h, repeats, threads_all=cores, frame_rows=spec == sizes[0])
        if spec == sizes[0]:
            rows += measure_nearfield(w, h, max(3, repeats // 3), patterns=24, label="nearfield (point, 72 obs)",
                                      threads_all=cores)
        if spec == sizes[0] or spec == "320x240":
            for solver in models:
                rows += measure_model(solver, w, h, repeats, store, threads_all=cores)
    device = None
    if getattr(args, "device", "cpu") != "cpu":
        device = measure_device(*(int(v) for v in sizes[0].split("x")), args.device, getattr(args, "batch", 256),
                                max(3, repeats // 5))
    startup = None if (quick or getattr(args, "no_startup", False)) else measure_startup()
    targets = []
    for (solver, size), fps in TARGETS.items():
        fast = [r for r in rows if r["solver"] == solver and r["size"] == size and r["path"] == "fast"]
        if not fast:
            continue
        best = max(fast, key=lambda r: r["fps"])
        ok = best["fps"] >= fps
        note = ""
        if solver == "nearfield":
            gap = best["error_deg"] - best["eager_error_deg"]
            ok = ok and gap <= ERROR_MARGIN_DEG
            note = f"; error {best['error_deg']:.3f} deg vs eager {best['eager_error_deg']:.3f} deg"
        targets.append({"solver": solver, "size": size, "target_fps": fps, "fps": best["fps"],
                        "threads": best["threads"], "met": bool(ok), "note": note})
    frames = [r for r in rows if r["path"] == "frames" and r["solver"] == "nearfield" and r["size"] == "320x240"]
    if frames and cores >= 16:  # on 16 cores: frames in parallel >= 2,000 fps and >= 8x one thread
        best = max(frames, key=lambda r: r["fps"])
        targets.append({"solver": "nearfield frames in parallel", "size": "320x240", "target_fps": 2000.0,
                        "fps": best["fps"], "threads": best["threads"],
                        "met": bool(best["fps"] >= 2000 and best["speedup"] >= 8),
                        "note": f"; {best['speedup']:.1f}x one thread (target 8x)"})
    default_solver, default_threads = _live_defaults()
    bench_rows = [{"knob": f"live {r['solver']} @ {r['size']}", "setting": f"{r['path']}, {r['threads']} thread(s)",
                   "error": r["error_deg"], "error_unit": "deg", "seconds": r["seconds"], "path": r["path"],
                   "device": "cpu", "threads": r["threads"], "size": r["size"], "seconds_runs": r.get("seconds_runs"),
                   "default": (r["solver"], r["path"], r["threads"]) == (default_solver, "fast", default_threads)}
                  for r in rows]
    if device:
        bench_rows += [{"knob": f"live nearfield @ {device['size']}", "setting": f"{device['device']} {r['solver']}, "
                        f"batches of {device['batch']}", "error": r["error_deg"], "error_unit": "deg",
                        "seconds": 1.0 / r["whole_numpy"]["frames_per_second"], "path": "gpu " + r["solver"],
                        "device": device["card"], "threads": None, "size": device["size"], "default": False}
                       for r in device["solvers"]]
    return {"rows": bench_rows, "measurements": rows, "targets": targets, "device": device, "startup": startup,
            "repeats": repeats, "cores": cores, "load_average": list(load) + list(os.getloadavg())}


def _live_defaults() -> tuple[str, int]:
    """``iristac live``'s default solver and threads, read from its command line (the live view
    always runs the fast path)."""
    from pipeline.cli import command_defaults
    from pipeline.cli.live import chosen_solver

    a = command_defaults("live", "--virtual")
    return chosen_solver(a), a.threads


def format_table(result: dict) -> str:
    la = result["load_average"]
    lines = [f"bench live: uint8 frames to heights (DST), best of {result['repeats']}; load average "
             f"{la[0]:.2f} before, {la[3]:.2f} after; {result['cores']} cores",
             f"{'solver':<28}{'size':>9} {'path':<6}{'thr':>4}{'ms':>9}{'fps':>9}{'err deg':>9}{'vs eager':>10}"]
    for r in result["measurements"]:
        dev = "-" if r["deviation_deg"] is None else f"{r['deviation_deg']:.2e}"
        lines.append(f"{r['solver']:<28}{r['size']:>9} {r['path']:<6}{r['threads']:>4}{r['seconds'] * 1e3:9.2f}"
                     f"{r['fps']:9.1f}{r['error_deg']:9.3f}{dev:>10}")
    lines.append("(err: mean angular error against the rendered truth; vs eager: the largest deviation of the fast "
                 "path's normals from the eager solver's, deg)")
    d = result.get("device")
    if d:
        from pipeline.bench.live_scaling import format_device

        lines += format_device(d)
    st = result.get("startup")
    if st:
        for k, v in st.items():
            if "error" in v:
                lines.append(f"start-up ({k}): failed: {v['error']}")
            else:
                lines.append(f"start-up ({k.replace('_', ' ')}): imports {v['import_s']:.2f} s, precompute "
                             f"{v['precompute_s']:.2f} s, first frame {v['first_frame_s']:.2f} s: "
                             f"{v['process_to_first_frame_s']:.2f} s from the first import to the first heights")
    for t in result["targets"]:
        lines.append(f"target {t['solver']} >= {t['target_fps']:.0f} fps at {t['size']}: "
                     f"{'met' if t['met'] else 'NOT met'} ({t['fps']:.1f} fps on {t['threads']} thread(s){t['note']})")
    return "\n".join(lines)
