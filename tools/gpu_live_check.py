"""GPU and many-core check of the live near-field path (tools/gpu_check.sh runs it).

The near-field fast path at 320 x 240 on this machine's cores (one frame split over threads, and
whole frames in parallel on 1, 2, 4, 8, 16 threads), then the GPU pipeline
(:func:`pipeline.bench.live_scaling.measure_device`): upload alone, solve alone, whole, with
the fused kernel and the torch solver. ``iristac bench live --device cuda`` prints the same
figures beside the LUT and MLP paths; this is the short form. Writes JSON to argv[1].
"""

from __future__ import annotations

import json
import os
import sys


def main() -> int:
    from pipeline.base.threads import limit_threads
    from pipeline.bench.live import measure_nearfield
    from pipeline.bench.live_scaling import format_device, measure_device

    batch = int(os.environ.get("GPU_BATCH", "256"))
    out = {"cores": os.cpu_count(), "load_average": list(os.getloadavg())}
    with limit_threads(torch=1, blas=1):
        rows = measure_nearfield(320, 240, 20, threads_all=os.cpu_count() or 1, frame_rows=True)
        out["cpu_rows"] = rows
        for r in rows:
            print(f"cpu {r['path']:<7}{r['threads']:>4} thr {r['seconds'] * 1e3:8.3f} ms {r['fps']:9.1f} fps "
                  f"err {r['error_deg']:.3f} speedup {r.get('speedup', '-')} normals alone "
                  f"{r.get('normals_fps', '-')} fps, depth alone {r.get('depth_fps', '-')} fps", flush=True)
        try:
            d = measure_device(320, 240, "cuda", batch, 20)
            out["device"] = d
            print("\n".join(format_device(d)), flush=True)
        except Exception as exc:  # noqa: BLE001 - the CPU figures above still count
            out["device_error"] = f"{type(exc).__name__}: {exc}"
            print("device failed:", out["device_error"], flush=True)
    if len(sys.argv) > 1:
        with open(sys.argv[1], "w") as f:
            json.dump(out, f, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
