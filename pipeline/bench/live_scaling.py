"""``iristac bench live``'s throughput measurements: frames in parallel on the CPU, and the GPU pipeline.

CPU (:func:`frame_parallel_rows`): ``K`` distinct copies of a frame set through
:class:`pipeline.frame_pipeline.cpu_batch.CPUFramePipeline` (normals by the batch kernel, each thread
a run of pixel blocks of every frame; then heights, each thread a run of frames) on ``N`` =
1, 2, 4, 8, 16 threads up to the cores; frames per second of the whole batch, the normals and
the depth alone, and the Python time a frame (what holds the GIL).

GPU (:func:`measure_device`): :class:`pipeline.frame_pipeline.gpu_stream.GPUFramePipeline` with the
fused kernel and with the torch einsum solver; the pinned upload alone, the solve alone on
frames already on the device (CUDA events), the whole from pinned host frames and from plain
numpy frames; each with its bound: the whole against the upload alone (PCIe), the solve
against the time the device's own copy bandwidth needs to read the frames and write the heights.
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["format_device", "frame_parallel_rows", "measure_device", "thread_counts", "mean_error_deg",
           "max_deviation_deg", "FOV_MM"]

#: Field of view (mm) of the live benchmark's frames (``pipeline.bench.live`` and this module).
FOV_MM = 16.0


def mean_error_deg(normals, truth, mask=None) -> float:
    """Mean angular error (deg) of ``normals (..., 3)`` against ``truth``, over ``mask`` if given."""
    from pipeline.results.evaluate import angular_error_deg

    e = angular_error_deg(np.asarray(normals, np.float64), truth)
    return float(e.mean() if mask is None else e[mask].mean())


def max_deviation_deg(a, b, mask) -> float:
    """Largest angle (deg) between two normal maps over ``mask`` (0 where the mask is empty)."""
    from pipeline.results.evaluate import angular_error_deg

    m = np.asarray(mask, bool)
    return float(angular_error_deg(np.asarray(a, np.float64)[m], np.asarray(b, np.float64)[m]).max()) if m.any() else 0.0


def thread_counts(cores: int) -> list[int]:
    """1, 2, 4, 8, 16 up to ``cores``, and ``cores`` itself."""
    out = [n for n in (1, 2, 4, 8, 16) if n <= cores]
    return out if cores in out else out + [cores]


def frame_parallel_rows(label: str, size: str, fast, dst, frames: np.ndarray, truth: np.ndarray, cores: int,
                        repeats: int, count: int = 128, per_frame: bool = False) -> list[dict]:
    """Rows ``path = "frames"``: ``count`` distinct frame sets through
    :class:`pipeline.frame_pipeline.cpu_batch.CPUFramePipeline` on ``N`` threads (the normals and the
    depth also timed alone); ``seconds`` is per frame (the batch's time over ``count``).
    ``serial_us``: the pipeline's Python time a frame (the same batch of 8 x 8 frames, whose
    compute is nil: all of it holds the GIL), and ``gil_busy`` its share of the batch's wall
    time (on one thread: of a frame's time; the lock is a bound once it nears 1). ``per_frame``: also rows ``path = "pool"``, one Python task per frame
    on :class:`pipeline.base.frame_pool.FramePool` (``fast.solve`` then ``dst.integrate``: the
    earlier design), for comparison."""
    from pipeline.frame_pipeline.cpu_batch import CPUFramePipeline

    batch = np.repeat(frames[None], count, axis=0)  # distinct memory per frame, as a recording has
    r0 = fast.solve(frames, 1)
    K, (H, W) = count, dst.shape
    height, valid = np.empty((K, H, W), np.float32), np.empty((K, H, W), np.bool_)
    runs = max(2, repeats // 10)
    rows: list[dict] = []
    base = None
    for n in thread_counts(cores):
        serial = _serial_seconds(count, runs, n)
        with CPUFramePipeline(fast, dst, threads=n) as pipe:
            pipe.run(batch[:n])  # warm: threads started, kernels loaded
            sec, out = _best_of(lambda p=pipe: p.run(batch, out=height), runs)
            planes = out["planes"]
            sec_n, _ = _best_of(lambda p=pipe: p.normals(batch), runs)
            sec_d, _ = _best_of(lambda p=pipe: dst.integrate_batch(planes.normals, planes.mask, p.pool,
                                                                   out=(height, valid)), runs)
        fps = count / sec
        base = base or fps
        last = planes.result(count - 1)
        rows.append({"solver": label, "size": size, "path": "frames", "threads": n, "seconds": sec / count,
                     "fps": fps, "error_deg": mean_error_deg(last.normals, truth),
                     "deviation_deg": max_deviation_deg(last.normals, r0.normals, last.mask & r0.mask), "frames": count,
                     "speedup": fps / base, "device": "cpu", "normals_fps": count / sec_n, "depth_fps": count / sec_d,
                     "serial_us": serial * 1e6 / count, "gil_busy": serial / sec})
    if per_frame:
        rows += _pool_rows(label, size, fast, dst, batch, truth, cores, runs)
    return rows


def _best_of(fn, runs: int):
    best, out = float("inf"), None
    for _ in range(runs):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def _serial_seconds(count: int, runs: int, threads: int) -> float:
    """The Python seconds of a batch of ``count`` frame sets on ``threads`` threads (what holds the
    GIL): the pipeline's time on 8 x 8 frames (whose compute is nil; one normals part there),
    plus handing out the other normals parts (one a thread) of a larger frame (no-op parts)."""
    from pipeline.bench.recon_scene import render_sphere_scene
    from pipeline.depth.fast import FastDST
    from pipeline.frame_pipeline.cpu_batch import CPUFramePipeline
    from pipeline.normals.fast import NearFieldFast

    s = render_sphere_scene((8, 8), 1.0, radius=3.0, depth=0.5, num_patterns=8, noise=1.0, bits=8, seed=0)
    tiny = np.repeat(s.frames.astype(np.uint8)[None], count, axis=0)
    fast = NearFieldFast(s.lights_flat(), groups=np.tile(np.arange(3), tiny.shape[1]))
    with CPUFramePipeline(fast, FastDST((8, 8), 1.0), threads=threads) as pipe:
        pipe.run(tiny)
        sec = _best_of(lambda: pipe.run(tiny), 5 * runs)[0]
        parts = threads - 1
        return sec + (_best_of(lambda: pipe.pool.split(lambda a, b: None, parts, parts=parts), 5 * runs)[0]
                      if parts else 0.0)


def _pool_rows(label: str, size: str, fast, dst, batch: np.ndarray, truth: np.ndarray, cores: int,
               runs: int) -> list[dict]:
    """Rows ``path = "pool"``: one Python task per frame (see :func:`frame_parallel_rows`)."""
    from pipeline.base.frame_pool import FramePool

    def one(f):
        r = fast.solve(f, 1)
        return r, dst.integrate(r.normals, r.mask, workers=1)

    count = len(batch)
    rows, base = [], None
    for n in thread_counts(cores):
        with FramePool(n) as pool:
            pool.map(one, batch[:n])  # warm
            sec, out = _best_of(lambda p=pool: p.map(one, batch), runs)
        fps = count / sec
        base = base or fps
        rows.append({"solver": label, "size": size, "path": "pool", "threads": n, "seconds": sec / count, "fps": fps,
                     "error_deg": mean_error_deg(out[-1][0].normals, truth), "deviation_deg": None, "frames": count,
                     "speedup": fps / base, "device": "cpu"})
    return rows


def _events_ms(fn, repeats: int) -> float:
    """Median milliseconds of ``fn`` on the current stream (CUDA events), after one warm-up."""
    import torch

    fn()
    times = []
    for _ in range(repeats):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn()
        b.record()
        b.synchronize()
        times.append(a.elapsed_time(b))
    return float(np.median(times))


def _copy_bandwidth(device) -> float:
    """The device's copy bandwidth, bytes/s (read + write) of a 2 GB device-to-device copy."""
    import torch

    x = torch.empty(1 << 30, dtype=torch.uint8, device=device).random_(0, 255)
    y = torch.empty_like(x)
    ms = _events_ms(lambda: y.copy_(x), 10)
    return 2 * x.numel() / (ms * 1e-3)


def measure_device(width: int, height: int, device: str, batch: int, repeats: int, batches: int = 8,
                   files: bool = True) -> dict:
    """The GPU pipeline at ``width x height`` (8 patterns, RGB, uint8): see the module docstring;
    ``files``: also from HDF5 files read straight into its pinned buffers (:func:`_from_files`)."""
    import torch

    from pipeline.bench.recon_scene import render_sphere_scene
    from pipeline.frame_pipeline.gpu_stream import GPUFramePipeline
    from pipeline.normals.fast import NearFieldFast

    dev = torch.device(device)
    if dev.index is None:
        dev = torch.device("cuda", torch.cuda.current_device())
    mm = FOV_MM / width
    s = render_sphere_scene((height, width), mm, radius=3.0, depth=0.5, num_patterns=8, noise=1.0, bits=8, seed=0)
    one = s.frames.astype(np.uint8)
    P = one.shape[0]
    cpu = NearFieldFast(s.lights_flat(), groups=np.tile(np.arange(3), P)).solve(one)
    K = batch * batches
    host = np.repeat(one[None], K, axis=0)
    pinned = torch.from_numpy(host).pin_memory()
    frame_bytes = one.nbytes
    bw = _copy_bandwidth(dev)
    d_frames = torch.empty((batch,) + one.shape, dtype=torch.uint8, device=dev)
    copy_ms = _events_ms(lambda: d_frames.copy_(pinned[:batch], non_blocking=True), repeats)
    out = {"device": str(device), "card": torch.cuda.get_device_name(dev), "size": f"{width}x{height}",
           "batch": batch, "frames": K, "frame_bytes": frame_bytes, "device_copy_GBps": bw / 1e9,
           "upload": {"ms_per_batch": copy_ms, "GBps": batch * frame_bytes / (copy_ms * 1e-3) / 1e9,
                      "frames_per_second": batch / (copy_ms * 1e-3)}, "solvers": []}
    upload_fps = out["upload"]["frames_per_second"]
    for name in ("fused", "torch"):
        t0 = time.perf_counter()
        pipe = GPUFramePipeline(s.lights, mm, batch=batch, solver=name, device=dev, host_threads=8)
        d_frames.copy_(pinned[:batch])
        r = pipe.solve_device(d_frames)
        torch.cuda.synchronize()
        first = time.perf_counter() - t0
        solve_ms = _events_ms(lambda p=pipe: p.solve_device(d_frames), repeats)
        normals_ms, depth_ms = _split_ms(pipe, d_frames, r, repeats)
        n0 = r["normals"][0].cpu().numpy()
        floor_ms = batch * (frame_bytes + 4 * width * height) / bw * 1e3
        row = {"solver": name, "first_batch_seconds": first, "error_deg": mean_error_deg(n0, s.normals),
               "cpu_error_deg": mean_error_deg(cpu.normals, s.normals),
               "deviation_from_cpu_deg": max_deviation_deg(n0, cpu.normals, r["mask"][0].cpu().numpy() & cpu.mask),
               "solve": {"ms_per_batch": solve_ms, "frames_per_second": batch / (solve_ms * 1e-3),
                         "memory_floor_fraction": floor_ms / solve_ms, "normals_ms": normals_ms,
                         "depth_ms": depth_ms}}
        outs = {"whole_pinned": (pinned, torch.empty((K, height, width), dtype=torch.float32, pin_memory=True)),
                "whole_numpy": (host, np.zeros((K, height, width), np.float32))}
        for label, (src, dest) in outs.items():
            pipe.run(src[:batch])  # warm the buffers
            best = float("inf")
            for _ in range(max(2, repeats // 5)):
                t = time.perf_counter()
                res = pipe.run(src, out=dest)
                best = min(best, time.perf_counter() - t)
            fps = K / best
            row[label] = {"seconds": best, "frames_per_second": fps, "upload_fraction": fps / upload_fps}
        h_gpu = np.asarray(res["height"][0])
        h_cpu = _cpu_height(cpu, (height, width), mm)
        row["height_max_diff_mm"] = float(np.abs(h_gpu - h_cpu)[cpu.mask].max()) if cpu.mask.any() else 0.0
        if name == "fused" and files:
            try:
                row.update(_from_files(pipe, host, repeats, upload_fps, h_cpu, cpu.mask))
            except Exception as exc:  # noqa: BLE001 - the figures above still count; say why these are missing
                row["files_error"] = f"{type(exc).__name__}: {exc}"
        pipe.close()
        out["solvers"].append(row)
    return out


def _from_files(pipe, host: np.ndarray, repeats: int, upload_fps: float, h_cpu: np.ndarray, mask: np.ndarray,
                lzf_frames: int = 64, where: str | None = None) -> dict:
    """The whole pipeline from HDF5 files read straight into its pinned buffers
    (:class:`pipeline.base.h5frames.H5Frames`): an unfiltered file of every frame (as
    ``iristac live --record`` writes; read by offsets on 8 threads), and ``lzf_frames`` of them
    written as a capture (before the frames layout: LZF, shuffle, Fletcher-32 chunks of one
    image through HDF5's filters on one thread; now Zstandard chunks decoded on 8 threads,
    :mod:`pipeline.base.frame_codec`). Each with the read alone into pinned memory (its bound). Files in
    a temporary folder under ``where`` (just written: in the page cache)."""
    import tempfile
    from pathlib import Path

    import torch

    from pipeline.base.frame_codec import h5py_with_filters
    from pipeline.base.h5frames import H5Frames
    from pipeline.base.store import Record, write_record

    h5py = h5py_with_filters()
    K, H, W = len(host), host.shape[2], host.shape[3]
    out: dict = {}
    with tempfile.TemporaryDirectory(prefix="iristac-h5-", dir=where) as d:
        plain, store = Path(d) / "frames.h5", Path(d) / "capture.h5"
        t = time.perf_counter()
        with h5py.File(plain, "w") as f:
            f.create_dataset("frames", data=host)
        write_seconds = time.perf_counter() - t
        P = host.shape[1]
        write_record(store, Record("capture", {"frames": host[:lzf_frames], "reference": host[0],
                                               "drive": np.zeros((P, 24, 3), np.float32),
                                               "brightness": np.ones(P, np.float32)},
                                   {"mm_per_px": 0.05, "pattern_names": [f"p{i}" for i in range(P)], "source": "bench"}))
        for label, path in (("whole_h5", plain), ("whole_h5_store", store)):
            with H5Frames(path, threads=8) as src:
                n = len(src)
                dest = torch.empty((n, H, W), dtype=torch.float32, pin_memory=True)
                staging = torch.empty((min(n, pipe.batch),) + host.shape[1:], dtype=torch.uint8, pin_memory=True)
                read, _ = _best_of(lambda s=src, b=staging: [s.read_into(b[:min(len(b), n - a)].numpy(), a,
                                                                        min(n, a + len(b)))
                                                             for a in range(0, n, len(b))], max(2, repeats // 5))
                whole, _ = _best_of(lambda s=src, o=dest: pipe.run(s, out=o), max(2, repeats // 5))
                fps = n / whole
                out[label] = {"frames": n, "direct": src.direct, "seconds": whole, "frames_per_second": fps,
                              "upload_fraction": fps / upload_fps, "read_alone_GBps": n * host[0].nbytes / read / 1e9,
                              "read_alone_frames_per_second": n / read,
                              "height_max_diff_mm": float(np.abs(dest.numpy() - h_cpu[None])[:, mask].max())}
        out["whole_h5"]["write_GBps"] = K * host[0].nbytes / write_seconds / 1e9
    return out


def _split_ms(pipe, d_frames, r, repeats: int) -> tuple[float, float]:
    """Milliseconds per batch of the normals alone and of the depth alone (its input kept)."""
    from pipeline.depth.batched import dst_divergence_torch, dst_heights

    if pipe.solver_name == "fused":
        normals = _events_ms(lambda: pipe.solver.solve_planes(d_frames), repeats)
        depth = _events_ms(lambda: pipe.depth.heights(r["planes"], r["planes_mask"]), repeats)
    else:
        normals = _events_ms(lambda: pipe.solver.solve(d_frames), repeats)
        depth = _events_ms(lambda: dst_heights(dst_divergence_torch(r["normals"], r["mask"], pipe.mm)[0]), repeats)
    return normals, depth


def _cpu_height(cpu_result, shape, mm) -> np.ndarray:
    from pipeline.depth.fast import FastDST

    return FastDST(shape, mm).integrate(cpu_result.normals, cpu_result.mask).height


def format_device(d: dict) -> list[str]:
    """Lines of the GPU pipeline's figures for ``bench live``'s table."""
    up = d["upload"]
    lines = [f"device {d['device']} ({d['card']}), {d['size']}, batches of {d['batch']} ({d['frames']} frames): "
             f"upload alone (pinned) {up['GBps']:.1f} GB/s = {up['frames_per_second']:.0f} frames/s; device copy "
             f"bandwidth {d['device_copy_GBps']:.0f} GB/s"]
    for r in d["solvers"]:
        sv = r["solve"]
        lines.append(f"  {r['solver']:<6} solve alone {sv['frames_per_second']:9.0f} frames/s "
                     f"({sv['memory_floor_fraction']:.0%} of the memory floor; normals {sv['normals_ms']:.2f} ms, "
                     f"depth {sv['depth_ms']:.2f} ms a batch); whole from pinned "
                     f"{r['whole_pinned']['frames_per_second']:8.0f} frames/s ({r['whole_pinned']['upload_fraction']:.0%}"
                     f" of the upload bound), from numpy {r['whole_numpy']['frames_per_second']:8.0f} frames/s "
                     f"({r['whole_numpy']['upload_fraction']:.0%}); error {r['error_deg']:.3f} deg (CPU "
                     f"{r['cpu_error_deg']:.3f}), vs CPU {r['deviation_from_cpu_deg']:.2e} deg, heights "
                     f"{r['height_max_diff_mm']:.1e} mm; first batch {r['first_batch_seconds']:.2f} s")
        if r.get("files_error"):
            lines.append(f"         from HDF5 files: failed: {r['files_error']}")
        for key, what in (("whole_h5", "an unfiltered HDF5 file"), ("whole_h5_store", "a store capture (LZF)")):
            h = r.get(key)
            if h:
                lines.append(f"         from {what}, {h['frames']} frames read into pinned buffers "
                             f"({'by offsets, 8 threads' if h['direct'] else 'through HDF5 filters'}): "
                             f"{h['frames_per_second']:8.0f} frames/s ({h['upload_fraction']:.0%} of the upload bound); "
                             f"the read alone {h['read_alone_GBps']:.1f} GB/s = {h['read_alone_frames_per_second']:.0f} "
                             f"frames/s; heights vs CPU {h['height_max_diff_mm']:.1e} mm")
    return lines
