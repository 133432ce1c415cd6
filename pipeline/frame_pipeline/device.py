"""The frame pipeline on a GPU: a chunk's normals and heights by the fused device pipeline.

``iristac batch --device cuda`` and ``reconstruct --device cuda`` with ``nearfield`` and ``dst``
on the whole frame solve each chunk with :meth:`pipeline.frame_pipeline.gpu_stream.GPUFramePipeline.solve_device`
(one fused kernel for the normals, the divergence and a batched FFT for the heights, on the
device; its ``torch`` variant, :class:`pipeline.normals.batched.NearFieldBatched`, anywhere torch
runs, the CPU included, which is how the path is tested without a GPU), then copy the normals,
heights and masks back for the store. The frames of a chunk go up in one copy.

Examples
--------
>>> import numpy as np
>>> from pipeline.frame_pipeline.gpu_stream import GPUFramePipeline
>>> rng = np.random.default_rng(0)
>>> L = rng.normal(size=(3, 3, 8, 8, 3)); L[..., 2] = np.abs(L[..., 2]) + 2   # (P, C, H, W, 3)
>>> gpu = GPUFramePipeline(L, 0.1, solver="torch", device="cpu", host_threads=1)
>>> out = DeviceFramePipeline(gpu).run(rng.integers(0, 255, size=(2, 3, 8, 8, 3), dtype=np.uint8))
>>> out.normals.shape, out.height.shape, out.mask.dtype
((2, 8, 8, 3), (2, 8, 8), dtype('bool'))
"""

from __future__ import annotations

import numpy as np

from pipeline.frame_pipeline.chunk import FrameBatch

__all__ = ["DeviceFramePipeline"]


class DeviceFramePipeline:
    """:meth:`~pipeline.frame_pipeline.FramePipeline.run`'s interface over a
    :class:`~pipeline.frame_pipeline.gpu_stream.GPUFramePipeline` (its ``fused`` or ``torch`` solve)."""

    def __init__(self, gpu):
        self.gpu = gpu
        self.threads = 1
        self.extras: tuple[str, ...] = ()
        self.contact_fn = None

    @property
    def method(self) -> str:
        return f"device ({self.gpu.solver_name}, {self.gpu.device})"

    def run(self, frames, normals=None, heights=None) -> FrameBatch:
        """Normals, heights and masks of frame sets ``(n, P, H, W, C)`` (integers)."""
        import torch

        if normals is not None or heights is not None:
            raise ValueError("DeviceFramePipeline solves frames; stored normals are integrated on the CPU")
        dev = torch.from_numpy(np.ascontiguousarray(frames)).to(self.gpu.device)
        r = self.gpu.solve_device(dev)
        n = len(frames)
        out = FrameBatch(r["normals"].float().cpu().numpy(), r["mask"].bool().cpu().numpy(),
                         r["height"].float().cpu().numpy(), r["height_mask"].bool().cpu().numpy(),
                         meta=[{"method": self.method} for _ in range(n)])
        if "albedo" in r:
            out.extras["albedo"] = r["albedo"].float().cpu().numpy()
        return out

    def close(self) -> None:
        self.gpu.close()

    def __enter__(self) -> DeviceFramePipeline:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
