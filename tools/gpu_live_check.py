"""GPU and many-core check of the live near-field path (tools/gpu_check.sh runs it).

The near-field fast path at 320 x 240 on this machine's cores: one frame split over threads,
frames in parallel on 1, 2, 4, 8, 16 threads (:class:`pipeline.frame_pipeline.cpu_batch.CPUFramePipeline`:
normals alone, depth alone, the Python time a frame that holds the GIL) beside the earlier one
Python task per frame (``pool`` rows), and the 16-core target; then the GPU pipeline
(:func:`pipeline.bench.live_scaling.measure_device`): upload alone, solve alone, whole from
pinned and from numpy frames, and from HDF5 files read straight into its pinned buffers, with
the fused kernel and the torch solver. ``iristac bench live --device cuda`` prints the same
figures beside the LUT and MLP paths; this is the short form. Writes JSON to argv[1] and the
headline lines to argv[2] (both optional).
"""

from __future__ import annotations

import json
import os
import sys
import time


def cpu_rows(out: dict, lines: list[str]) -> None:
    from pipeline.bench.live import measure_nearfield

    cores = os.cpu_count() or 1
    t = time.perf_counter()
    rows = measure_nearfield(320, 240, 20, threads_all=cores, frame_rows="compare")
    out["cpu_rows"] = rows
    out["cpu_seconds"] = time.perf_counter() - t
    for r in rows:
        extra = ""
        if r["path"] == "frames":
            extra = (f" speedup {r['speedup']:.2f}x; normals alone {r['normals_fps']:.0f} fps, depth alone "
                     f"{r['depth_fps']:.0f} fps; Python {r['serial_us']:.1f} us a frame, GIL busy {r['gil_busy']:.1%}")
        elif r["path"] == "pool":
            extra = f" speedup {r['speedup']:.2f}x"
        dev = "-" if r.get("deviation_deg") is None else f"{r['deviation_deg']:.1e}"
        line = (f"cpu {r['path']:<7}{r['threads']:>4} thr {r['seconds'] * 1e3:8.3f} ms {r['fps']:9.1f} fps "
                f"err {r['error_deg']:.3f} vs eager/per-frame {dev}{extra}")
        print(line, flush=True)
        if r["path"] in ("frames", "pool"):
            lines.append(line)
    frames = [r for r in rows if r["path"] == "frames"]
    if frames:
        best = max(frames, key=lambda r: r["fps"])
        met = best["fps"] >= 2000 and best["speedup"] >= 8
        line = (f"target CPU frames in parallel >= 2,000 fps and >= 8x one thread ({cores} cores): "
                f"{'met' if met else 'NOT met'} ({best['fps']:.0f} fps on {best['threads']} threads, "
                f"{best['speedup']:.1f}x)")
        print(line, flush=True)
        lines.append(line)


def device_rows(out: dict, lines: list[str]) -> None:
    from pipeline.bench.live_scaling import format_device, measure_device

    batch = int(os.environ.get("GPU_BATCH", "256"))
    t = time.perf_counter()
    d = measure_device(320, 240, "cuda", batch, 20, files=os.environ.get("GPU_FILES", "1") != "0")
    out["device"] = d
    out["device_seconds"] = time.perf_counter() - t
    text = format_device(d)
    print("\n".join(text), flush=True)
    lines += text
    fused = next((r for r in d["solvers"] if r["solver"] == "fused"), None)
    if fused:
        for key in ("whole_pinned", "whole_numpy", "whole_h5", "whole_h5_store"):
            if key in fused:
                fps = fused[key]["frames_per_second"]
                lines.append(f"target GPU >= 20,000 fps, {key}: {'met' if fps >= 20000 else 'NOT met'} ({fps:.0f})")


def main() -> int:
    from pipeline.base.threads import limit_threads

    out: dict = {"cores": os.cpu_count(), "load_average_start": list(os.getloadavg())}
    lines: list[str] = []
    with limit_threads(torch=1, blas=1):
        for name, part in (("cpu", cpu_rows), ("device", device_rows)):
            if os.environ.get(f"GPU_SKIP_{name.upper()}"):
                continue
            try:
                part(out, lines)
            except Exception as exc:  # noqa: BLE001 - the other part's figures still count
                out[f"{name}_error"] = f"{type(exc).__name__}: {exc}"
                lines.append(f"{name} failed: {out[f'{name}_error']}")
                print(lines[-1], flush=True)
    out["load_average_end"] = list(os.getloadavg())
    lines.append(f"load average {out['load_average_start'][0]:.2f} at the start, {out['load_average_end'][0]:.2f} "
                 f"at the end")
    if len(sys.argv) > 1:
        with open(sys.argv[1], "w") as f:
            json.dump(out, f, indent=1, default=float)
    if len(sys.argv) > 2:
        with open(sys.argv[2], "w") as f:
            f.write("\n".join(lines) + "\n")
    return 1 if any(k.endswith("_error") for k in out) else 0


if __name__ == "__main__":
    sys.exit(main())
