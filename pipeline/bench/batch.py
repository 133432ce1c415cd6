"""``iristac bench batch``: batch processing of recordings, frames/s and peak memory against length.

For the LUT, the MLP and the near-field solver at one image size (default 320 x 240), on the
same calibrations ``iristac bench live`` uses (the virtual sensor in trichromatic mode, calibrated
as ``live --virtual`` does; the bare 24-LED ring's exact light field in the 8-sector monochromatic
mode for the near field):

- **live**: ``bench live``'s figure for the same solver, measured in this run
  (:func:`pipeline.bench.live.measure_model`, :func:`~pipeline.bench.live.measure_nearfield`:
  the fast path on one frame, best of the repeats, on one thread and on every core);
- **batch**: ``iristac batch REC --threads T --json`` in a new process on recordings of each
  length, written to disk first as a user's would be (store captures: presses rendered, the
  recording their sequence repeated with its own noise), from the capture on disk to the results
  on disk: its own frames/s (frames solved from the first frame read to the last result written
  and fsynced; its start-up, loading the light model, planning and the solvers' precomputation,
  printed apart) and the process's peak resident memory. A fresh store each run.

The issue's targets, printed with the figures: batch at 2,000 frames at least 80 % of live's
frames/s for the same solver and thread count; peak memory at the longest recording at most 1.2x
that at the shortest. The error column is the batch's own mean normal error on the shortest
recording, which carries the rendered truth (the longer ones do not: a real recording has none,
and the comparison with truth costs time a user's run does not spend).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["add_arguments", "run", "format_table", "SPEED_TARGET", "MEMORY_TARGET"]

#: batch frames/s over live frames/s (same solver and threads) to reach at 2,000 frames.
SPEED_TARGET = 0.8
#: peak memory at the longest recording over the shortest's, at most.
MEMORY_TARGET = 1.2
#: Distinct rendered presses a recording cycles through.
PRESSES = 64


def add_arguments(parser) -> None:
    parser.add_argument("--size", default="320x240", metavar="WxH", help="image size (default 320x240)")
    parser.add_argument("--lengths", nargs="*", type=int, default=None,
                        help="recording lengths in frames (default 500 2000 10000; the near field's 8-pattern "
                             "recordings stop at 2000: 1.8 MB a frame set)")
    parser.add_argument("--solvers", nargs="*", default=None, choices=("lut", "mlp", "nearfield"),
                        help="solvers (default all three)")
    parser.add_argument("--repeats", type=int, default=None, help="live timing repeats (default 30)")
    parser.add_argument("--cache", default=None, help="stage store for the virtual sensor's calibrations")
    parser.add_argument("--workdir", default=None, help="where the recordings go (default a temporary folder)")


def _recording(path: Path, model, mode: str, frames: int, truth: bool, seed: int) -> float:
    """A store capture of ``frames`` frame sets (``PRESSES`` rendered presses in sequence, each
    repeat with its own noise); returns the seconds it took to write."""
    from pipeline.base.capture import write_capture
    from sim.contacts import contact_surfaces
    from sim.rendered_capture import render_capture

    H, W = model.shape
    mm = model.mm_per_px
    surfaces = contact_surfaces("sphere", (H, W), mm, min(PRESSES, frames), size_mm=2.0, depth_mm=0.5,
                                spread_mm=0.25 * H * mm, seed=seed)
    cap = render_capture(model, mode, surfaces, noise_dn=0.0, bit_depth=None, seed=seed)
    clean = cap.data["frames"].astype(np.float32)  # (n, P, H, W, C) without noise
    rng = np.random.default_rng(seed)
    idx = np.arange(frames) % len(clean)
    out = np.empty((frames,) + clean.shape[1:], np.uint8)
    for a in range(0, frames, 256):
        b = min(frames, a + 256)
        noisy = clean[idx[a:b]] + rng.normal(0.0, 1.0, (b - a,) + clean.shape[1:]).astype(np.float32)
        out[a:b] = np.clip(np.round(noisy), 0, 255).astype(np.uint8)
    cap.data["frames"] = out
    cap.data["reference"] = np.clip(np.round(cap.data["reference"]), 0, 255).astype(np.uint8)
    if "dark" in cap.data:
        cap.data["dark"] = np.clip(np.round(cap.data["dark"]), 0, 255).astype(np.uint8)
    for name in list(cap.data):
        if name.startswith("truth/"):
            if truth and np.shape(cap.data[name])[:1] == (len(clean),):
                cap.data[name] = cap.data[name][idx]
            elif truth:
                continue
            else:
                del cap.data[name]
    cap.meta["bit_depth"] = 8
    t = time.perf_counter()
    write_capture(path, cap)
    return time.perf_counter() - t


def _light_file(solver: str, w: int, h: int, store, workdir: Path):
    """``(model, flag, light file, lighting mode)`` of a solver: the calibration bench live uses."""
    from pipeline.base.store import write_record
    from pipeline.bench.live import sensor_calibration
    from pipeline.bench.live_scaling import FOV_MM
    from pipeline.stages.synthesize import illumination_record
    from sim.render import bare_ring_illumination

    if solver == "nearfield":
        model = bare_ring_illumination((h, w), FOV_MM / w)
        path = write_record(workdir / "illumination.h5", illumination_record(model))
        return model, "--illumination", path, "monochromatic"
    model, cal = sensor_calibration(store, w, h, solver)
    return model, "--calibration", cal.path, "trichromatic"


def _batch(rec: Path, flag: str, light, solver: str, threads: int, cache: Path, workers: int = 1) -> dict:
    """``iristac batch`` in a new process: its JSON summary (frames/s, peak memory)."""
    import pipeline

    repo = str(Path(pipeline.__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=repo + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "pipeline", "batch", str(rec), flag, str(light), "--solver", solver,
           "--threads", str(threads), "--cache", str(cache), "--json", "--workers", str(workers)]
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=3600)
    wall = time.perf_counter() - t
    shutil.rmtree(cache, ignore_errors=True)
    if r.returncode != 0:
        return {"error": (r.stderr or r.stdout)[-500:]}
    out = json.loads(r.stdout)
    item = out["items"][0]
    return {"fps": out["frames_per_second"], "peak_rss_mb": max(out["peak_rss_mb"], out["peak_rss_workers_mb"]),
            "seconds": out["seconds"],
            "startup_seconds": out["startup_seconds"],
            "process_seconds": wall, "frames": out["frames"],
            "error_deg": (item.get("result") or {}).get("normal_mean_error_deg")}


def _live(solver: str, w: int, h: int, repeats: int, store, cores: int) -> dict[int, dict]:
    """``bench live``'s fast rows of ``solver``: threads -> row."""
    from pipeline.bench.live import measure_model, measure_nearfield

    rows = (measure_nearfield(w, h, repeats, threads_all=cores) if solver == "nearfield"
            else measure_model(solver, w, h, repeats, store, threads_all=cores))
    return {r["threads"]: r for r in rows if r["path"] == "fast" and r["solver"] == solver}


def run(args) -> dict:
    """Measure (see the module docstring)."""
    from pipeline.base.store import StageStore
    from pipeline.base.threads import limit_threads

    quick = getattr(args, "quick", False)
    size = getattr(args, "size", None) or "320x240"
    w, h = (int(v) for v in ("160x120" if quick and size == "320x240" else size).lower().split("x"))
    lengths = getattr(args, "lengths", None) or ([40, 120] if quick else [500, 2000, 10000])
    solvers = getattr(args, "solvers", None) or (["lut"] if quick else ["lut", "mlp", "nearfield"])
    repeats = getattr(args, "repeats", None) or (5 if quick else 30)
    cores = os.cpu_count() or 1
    threads = sorted({1, cores})
    store = StageStore(getattr(args, "cache", None))
    work = Path(getattr(args, "workdir", None) or tempfile.mkdtemp(prefix="iristac-bench-batch-"))
    work.mkdir(parents=True, exist_ok=True)
    rows, live = [], {}
    load = os.getloadavg()
    try:
        for solver in solvers:
            with limit_threads(torch=1, blas=1):
                live[solver] = _live(solver, w, h, repeats, store, cores)
            model, flag, light, mode = _light_file(solver, w, h, store, work)
            lens = [n for n in lengths if solver != "nearfield" or n <= 2000 or getattr(args, "lengths", None)]
            for i, n in enumerate(lens):
                rec = work / f"{solver}-{n}.h5"
                # The shortest of several carries the rendered truth (its error column).
                write_s = _recording(rec, model, mode, n, truth=i == 0 and len(lens) > 1, seed=11 + i)
                for th in threads:
                    r = _batch(rec, flag, light, solver, th, work / "store")
                    lv = live[solver].get(th, {})
                    rows.append({"solver": solver, "frames": n, "threads": th, "live_fps": lv.get("fps"),
                                 "live_error_deg": lv.get("error_deg"), "write_seconds": write_s,
                                 "recording_mb": rec.stat().st_size / 2**20, **r})
                if solver == solvers[0] and n == (2000 if 2000 in lens else lens[-1]) and cores > 1:
                    # Frame ranges on local worker processes (one thread each): against one worker.
                    for wk in (1, cores):
                        r = _batch(rec, flag, light, solver, 1, work / "store", workers=wk)
                        rows.append({"solver": solver, "frames": n, "threads": 1, "workers": wk,
                                     "recording_mb": rec.stat().st_size / 2**20, "live_fps": None, **r})
                rec.unlink()
    finally:
        if getattr(args, "workdir", None) is None:
            shutil.rmtree(work, ignore_errors=True)
    return _result(rows, lengths, cores, load, w, h, repeats)


def _result(rows, lengths, cores, load, w, h, repeats) -> dict:
    targets = []
    for r in rows:
        if r.get("fps") and r.get("live_fps"):
            r["ratio"] = r["fps"] / r["live_fps"]
    pooled = {r["workers"]: r for r in rows if r.get("workers") and r.get("fps")}
    if len(pooled) > 1:
        one, many = pooled[min(pooled)], pooled[max(pooled)]
        targets.append({"what": f"{max(pooled)} local workers >= 1.7x one ({one['solver']}, {one['frames']:,} frames, "
                                f"a thread each)", "met": many["fps"] >= 1.7 * one["fps"],
                        "value": f"{many['fps'] / one['fps']:.2f}x ({many['fps']:.0f} against {one['fps']:.0f} "
                                 f"frames/s; worker start-up apart, as a thread's)"})
    rows_main = [r for r in rows if not r.get("workers")]
    for solver in dict.fromkeys(r["solver"] for r in rows_main):
        mine = [r for r in rows_main if r["solver"] == solver and "fps" in r]
        for r in mine:
            if r["frames"] == 2000 and r.get("ratio") is not None:
                targets.append({"what": f"{solver} batch >= {SPEED_TARGET:.0%} of live at 2,000 frames, "
                                        f"{r['threads']} thread(s)", "met": r["ratio"] >= SPEED_TARGET,
                                "value": f"{r['ratio']:.0%} ({r['fps']:.0f} against {r['live_fps']:.0f} frames/s)"})
        for th in dict.fromkeys(r["threads"] for r in mine):
            by_n = {r["frames"]: r["peak_rss_mb"] for r in mine if r["threads"] == th}
            if len(by_n) > 1:
                lo, hi = by_n[min(by_n)], by_n[max(by_n)]
                targets.append({"what": f"{solver} peak memory at {max(by_n):,} frames <= {MEMORY_TARGET}x "
                                        f"{min(by_n):,}'s, {th} thread(s)", "met": hi <= MEMORY_TARGET * lo,
                                "value": f"{hi:.0f} MB against {lo:.0f} MB ({hi / lo:.2f}x)"})
    errors = {r["solver"]: r["error_deg"] for r in rows_main if r.get("error_deg") is not None}
    bench_rows = [{"knob": f"batch {r['solver']} @ {w}x{h}", "setting": f"{r['frames']} frames, {r['threads']} "
                   f"thread(s)", "error": errors.get(r["solver"], r.get("live_error_deg")), "error_unit": "deg",
                   "seconds": 1.0 / r["fps"], "threads": r["threads"], "size": f"{w}x{h}", "frames": r["frames"],
                   "path": "batch", "device": "cpu", "peak_rss_mb": r["peak_rss_mb"], "default": False}
                  for r in rows_main if r.get("fps")]
    return {"rows": bench_rows, "measurements": rows, "targets": targets, "cores": cores, "size": f"{w}x{h}",
            "repeats": repeats, "load_average": list(load) + list(os.getloadavg())}


def format_table(result: dict) -> str:
    la = result["load_average"]
    lines = [f"bench batch: recordings on disk to results on disk at {result['size']} (iristac batch in a new "
             f"process, fresh store); live = bench live's fast path on one frame, best of {result['repeats']}; "
             f"{result['cores']} cores; load average {la[0]:.2f} before, {la[3]:.2f} after",
             f"{'solver':<10}{'frames':>8}{'thr':>5}{'batch fps':>11}{'live fps':>10}{'batch/live':>11}"
             f"{'peak MB':>9}{'err deg':>9}{'rec MB':>9}{'start s':>9}"]
    for r in result["measurements"]:
        if "error" in r and "fps" not in r:
            lines.append(f"{r['solver']:<10}{r['frames']:>8}{r['threads']:>5}  FAILED: {r['error']}")
            continue
        ratio = "-" if r.get("ratio") is None else f"{r['ratio']:.0%}"
        if r.get("workers"):
            lines.append(f"{r['solver']:<10}{r['frames']:>8}{'w' + str(r['workers']):>5}{r['fps']:>11.1f}"
                         f"{'(workers)':>10}{'-':>11}{r['peak_rss_mb']:>9.0f}{'-':>9}{r['recording_mb']:>9.0f}"
                         f"{r['startup_seconds']:>9.2f}")
            continue
        err = "-" if r.get("error_deg") is None else f"{r['error_deg']:.3f}"
        live = "-" if r.get("live_fps") is None else f"{r['live_fps']:.1f}"
        lines.append(f"{r['solver']:<10}{r['frames']:>8}{r['threads']:>5}{r['fps']:>11.1f}{live:>10}{ratio:>11}"
                     f"{r['peak_rss_mb']:>9.0f}{err:>9}{r['recording_mb']:>9.0f}{r['startup_seconds']:>9.2f}")
    lines.append("(batch fps: frames solved from the first frame read to the last result on disk; start s: the "
                 "batch's start-up before it, apart; err: its mean normal error against the rendered truth of the "
                 "shortest recording)")
    for t in result["targets"]:
        lines.append(f"target {t['what']}: {'met' if t['met'] else 'NOT met'} ({t['value']})")
    return "\n".join(lines)
