"""Host uint8 frames to normals and DST heights on a CUDA device, uploads overlapped with compute.

A batch of 320 x 240 frames under 8 patterns is 1.8 MB a frame: at 20,000 frames/s that is
37 GB/s over PCIe, so the upload, not the solve, sets the pace. :class:`GPUFramePipeline`
keeps it busy: two pinned host buffers and two device buffers, a copy stream and a compute
stream. While batch ``k`` is solved (:class:`pipeline.normals.gpu_nearfield.NearFieldGPU`,
one fused kernel; then :func:`~pipeline.depth.batched.dst_divergence_torch` and the batched
FFT :func:`~pipeline.depth.batched.dst_heights`), batch ``k + 1`` is staged into pinned memory
by host threads (or read there straight from an HDF5 file: :class:`pipeline.base.h5frames.H5Frames`)
and uploaded on the copy stream, and batch ``k - 1``'s heights come back on
the compute stream (PCIe is full duplex). Events order the reuse of each buffer.

``iristac bench live --device cuda`` times the copy alone, the solve alone (frames already on
the device) and the whole, and prints each as a fraction of its bound (the measured pinned
upload rate; the device's measured copy bandwidth).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

__all__ = ["GPUFramePipeline", "parallel_copy"]


def parallel_copy(dst: np.ndarray, src: np.ndarray, pool: ThreadPoolExecutor | None, parts: int) -> None:
    """``dst[...] = src`` split along the first axis over ``parts`` threads of ``pool`` (numpy's copy
    releases the GIL; one core copies about a third of what the memory moves)."""
    n = len(src)
    if pool is None or parts <= 1 or n < 2:
        np.copyto(dst, src)
        return
    step = -(-n // parts)
    futures = [pool.submit(np.copyto, dst[a:a + step], src[a:a + step]) for a in range(0, n, step)]
    for f in futures:
        f.result()


class GPUFramePipeline:
    """Near-field normals + DST heights of many frames on ``device``, batch after batch.

    Parameters
    ----------
    lights : ndarray (P, C, H, W, 3)
    mm_per_px : float
    batch : int
        Frames per upload and per launch.
    dark, flat_field, max_condition :
        As :class:`pipeline.normals.gpu_nearfield.NearFieldGPU`.
    solver : ``fused`` (the one-kernel solve) or ``torch`` (:class:`pipeline.normals.batched.NearFieldBatched`).
    host_threads : int
        Threads that stage frames into pinned memory.
    device : str
    """

    def __init__(self, lights, mm_per_px: float, *, batch: int = 256, dark=None, flat_field=None,
                 max_condition: float = 1e3, solver: str = "fused", host_threads: int = 4, device="cuda"):
        import torch

        from pipeline.normals.batched import NearFieldBatched
        from pipeline.normals.gpu_nearfield import NearFieldGPU

        if solver not in ("fused", "torch"):
            raise ValueError(f"GPUFramePipeline: solver must be 'fused' or 'torch', got {solver!r}")
        self.device = torch.device(device)
        self.mm = float(mm_per_px)
        self.batch = int(batch)
        self.solver_name = solver
        if solver == "fused":
            from pipeline.depth.gpu_dst import GPUDST

            self.solver = NearFieldGPU(lights, flat_field=flat_field, max_condition=max_condition, dark=dark,
                                       device=self.device)
            self._dark = None
            self.depth = GPUDST(self.solver.shape, self.mm, device=self.device)
        else:
            self.solver = NearFieldBatched(lights, flat_field=flat_field, max_condition=max_condition,
                                           device=self.device)
            self._dark = dark
        self.P, self.C, self.shape = self.solver.P, self.solver.C, self.solver.shape
        self.host_threads = max(1, int(host_threads))
        self._pool = ThreadPoolExecutor(self.host_threads, thread_name_prefix="iristac-stage") \
            if self.host_threads > 1 else None
        self._buffers = None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def solve_device(self, frames) -> dict:
        """Normals and heights of a batch already on the device (torch uint8 ``(B, P, H, W, C)``), on
        torch's current stream: the solve alone. Returns device tensors (``height (B, H, W)`` added)."""
        from pipeline.depth.batched import dst_divergence_torch, dst_heights

        if self.solver_name == "fused":  # two kernels (normals; divergence into the FFT's input), cuFFT
            n, _, _, ok = self.solver.solve_planes(frames)
            h, valid = self.depth.heights(n, ok)
            B = n.shape[0]
            H, W = self.shape
            return {"normals": n.permute(0, 2, 1).reshape(B, H, W, 3), "mask": ok.reshape(B, H, W).bool(),
                    "height": h, "height_mask": valid, "planes": n, "planes_mask": ok}
        r = self.solver.solve(frames, dark=self._dark)
        f, valid = dst_divergence_torch(r["normals"], r["mask"], self.mm)
        r["height"] = dst_heights(f)
        r["height_mask"] = valid
        return r

    def _alloc(self, dtype):
        import torch

        H, W = self.shape
        shape = (self.batch, self.P, H, W, self.C)
        if self._buffers is None or self._buffers["dtype"] != dtype:
            self._buffers = {
                "dtype": dtype,
                "pinned": [torch.empty(shape, dtype=dtype, pin_memory=True) for _ in range(2)],
                "device": [torch.empty(shape, dtype=dtype, device=self.device) for _ in range(2)],
                "heights": [torch.empty((self.batch, H, W), dtype=torch.float32, pin_memory=True) for _ in range(2)],
            }
        return self._buffers

    def run(self, frames, normals: bool = False, out=None) -> dict:
        """Heights ``(K, H, W)`` float32 (and ``normals (K, H, W, 3)`` when asked) of host frames
        ``(K, P, H, W, C)`` uint8/uint16.

        ``frames``: numpy (staged into pinned memory by host threads), an already pinned torch
        tensor (not staged again), or a frame source with ``read_into(dst, start, stop)``,
        ``shape`` and ``dtype`` (:class:`pipeline.base.h5frames.H5Frames`: an HDF5 capture or
        recording), which reads each batch straight into the pinned buffer.

        ``out``: where the heights go, a numpy array or a pinned torch tensor ``(K, H, W)`` float32
        (a pinned one receives them straight from the device, no host copy); None: a new array."""
        import torch

        reader = frames if hasattr(frames, "read_into") else None
        if reader is not None:
            src = None
            shape, dtype = tuple(reader.shape), torch.from_numpy(np.empty(0, reader.dtype)).dtype
        else:
            src = frames if isinstance(frames, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(frames))
            shape, dtype = tuple(src.shape), src.dtype
        K = shape[0]
        if shape[1:] != (self.P,) + self.shape + (self.C,):
            raise ValueError(f"GPUFramePipeline.run: frames must be (K, {self.P}, {self.shape[0]}, {self.shape[1]}, "
                             f"{self.C}), got {shape}")
        pinned = src is not None and src.is_pinned()
        bufs = self._alloc(dtype)
        H, W = self.shape
        if out is None:
            out = np.empty((K, H, W), np.float32)
        if tuple(out.shape) != (K, H, W):
            raise ValueError(f"GPUFramePipeline.run: out must be ({K}, {H}, {W}), got {tuple(out.shape)}")
        direct = isinstance(out, torch.Tensor) and out.is_pinned() and out.dtype == torch.float32
        out_n = np.empty((K, H, W, 3), np.float32) if normals else None
        copy_s, comp_s = torch.cuda.Stream(self.device), torch.cuda.Stream(self.device)
        uploaded = [torch.cuda.Event() for _ in range(2)]
        done = [torch.cuda.Event() for _ in range(2)]
        pending = []  # (slot, start, count, normals tensor or None) whose heights are on their way back
        starts = list(range(0, K, self.batch))
        for i, s in enumerate(starts):
            k = i % 2
            nb = min(self.batch, K - s)
            if i >= 2:  # slot k's last batch: its upload has been read and its heights copied out
                done[k].synchronize()
                self._finish(pending.pop(0), out, out_n)
            if pinned:
                host = src[s:s + nb]
            else:
                host = bufs["pinned"][k][:nb]
                if reader is not None:
                    reader.read_into(host.numpy(), s, s + nb)
                else:
                    parallel_copy(host.numpy(), src[s:s + nb].numpy(), self._pool, self.host_threads)
            with torch.cuda.stream(copy_s):
                dev = bufs["device"][k][:nb]
                dev.copy_(host, non_blocking=True)
                uploaded[k].record(copy_s)
            with torch.cuda.stream(comp_s):
                comp_s.wait_event(uploaded[k])
                r = self.solve_device(dev)
                dest = out[s:s + nb] if direct else bufs["heights"][k][:nb]
                dest.copy_(r["height"], non_blocking=True)
                nrm = r["normals"].to("cpu", non_blocking=False) if normals else None
                done[k].record(comp_s)
            pending.append((k, s, nb, nrm, direct))
        for item in pending:
            done[item[0]].synchronize()
            self._finish(item, out, out_n)
        res = {"height": out}
        if normals:
            res["normals"] = out_n
        return res

    def _finish(self, item, out, out_n) -> None:
        k, s, nb, nrm, direct = item
        if not direct:
            dst = out[s:s + nb].numpy() if hasattr(out, "numpy") else out[s:s + nb]
            parallel_copy(dst, self._buffers["heights"][k][:nb].numpy(), self._pool, self.host_threads)
        if out_n is not None:
            out_n[s:s + nb] = nrm.numpy()
