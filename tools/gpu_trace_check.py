"""GPU ray tracer check (tools/gpu_check.sh runs it): compile time, CPU/GPU agreement, rates.

1. the CUDA kernel compiled (or loaded from the disk cache) for float32, seconds;
2. the same rays on the CPU kernel (every core) and on the GPU: energy books, counters and the
   binned images (E and V, 24 LED azimuths, 60 x 60 px) at 1e6 and 1e7 rays;
3. the CPU kernel on 1, 2, 4, 8, 16 threads (up to the cores): rays/s and speed-up.

Prints one JSON object last (also written to the path given as the first argument).
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np


def main() -> int:
    from sim.optics import engine
    from sim.optics.grid import ImageBins, PixelGrid
    from sim.optics.multisource import led_azimuths
    from sim.scene import load_scene

    out: dict = {"cores": os.cpu_count()}
    t = time.perf_counter()
    out["gpu_compile_seconds"] = engine.warm_up(np.float32, "cuda")
    out["gpu_compile_wall_seconds"] = time.perf_counter() - t
    out["cpu_compile_seconds"] = engine.warm_up(np.float32, "cpu")
    s = load_scene("default")
    lay = ImageBins(PixelGrid((60, 60), (16.0 / 60, 16.0 / 60), s.plane.z), led_azimuths(s), vector=True).layout
    out["agreement"] = []
    for n in (1_000_000, 10_000_000):
        for sampler in ("grid", "random"):
            t = time.perf_counter()
            (a,), ta = engine.trace_led(s, [lay], rays=n, sampler=sampler)
            tc = time.perf_counter() - t
            t = time.perf_counter()
            (b,), tb = engine.trace_led(s, [lay], rays=n, sampler=sampler, device="cuda")
            tg = time.perf_counter() - t
            ea, eb = ta.energy.as_dict(), tb.energy.as_dict()
            row = {"rays": n, "sampler": sampler, "cpu_seconds": tc, "gpu_seconds": tg,
                   "energy_max_diff": max(abs(ea[k] - eb[k]) for k in ea),
                   "counters_equal": ta.counters == tb.counters, "cpu_counters": ta.counters,
                   "gpu_counters": tb.counters,
                   "E_rel_l1": float(np.abs(a[..., 0] - b[..., 0]).sum() / np.abs(a[..., 0]).sum()),
                   "V_rel_l1": float(np.abs(a[..., 1:] - b[..., 1:]).sum() / np.abs(a[..., 1:]).sum()),
                   "E_max_rel": float(np.abs(a[..., 0] - b[..., 0]).max() / np.abs(a[..., 0]).max())}
            out["agreement"].append(row)
            print(json.dumps(row), flush=True)
    # CPU threads (the kernel's own slot threads): 2e7 rays of one LED
    rows = []
    base = None
    cores = os.cpu_count() or 1
    for th in [c for c in (1, 2, 4, 8, 16) if c <= cores]:
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            engine.trace_led(s, [lay], rays=20_000_000, sampler="random", threads=th)
            best = min(best, time.perf_counter() - t)
        rate = 2e7 / best
        base = base or rate
        rows.append({"threads": th, "rays_per_second": rate, "speedup": rate / base})
        print(json.dumps(rows[-1]), flush=True)
    out["cpu_threads"] = rows
    text = json.dumps(out, indent=1)
    if len(sys.argv) > 1:
        with open(sys.argv[1], "w") as f:
            f.write(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
