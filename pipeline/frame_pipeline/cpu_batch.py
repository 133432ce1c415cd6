"""Many uint8 frames to near-field normals and DST heights on every CPU core, a batch at a time.

The CPU counterpart of :class:`pipeline.frame_pipeline.gpu_stream.GPUFramePipeline`, for throughput
(recordings, captures of many contact instances, ``iristac bench live``'s frames rows). A batch
of ``K`` frame sets goes through two phases on the threads of one
:class:`pipeline.base.frame_pool.FramePool`:

1. normals: :meth:`pipeline.normals.fast.NearFieldFast.solve_batch`, each thread a few runs of
   512-pixel blocks of every frame in one compiled call (a block's factors read once a batch,
   the frames de-interleaved in the kernel);
2. depth: :meth:`pipeline.depth.fast.FastDST.integrate_batch`, each thread a few runs of
   frames (divergence, DST, division by the eigenvalues, inverse DST over the run).

So Python and its lock are entered a few times per thread and batch, not per frame (one Python
task per frame, :meth:`~pipeline.base.frame_pool.FramePool.map` of the per-frame path, kept the
lock busy enough to stop scaling at 8 of 16 cores). Numbers are those of the per-frame path
(:meth:`~pipeline.normals.fast.NearFieldFast.solve`, :meth:`~pipeline.depth.fast.FastDST.integrate`)
to float rounding: ``tests/pipeline/normals/test_fast_paths.py``.
"""

from __future__ import annotations

import numpy as np

from pipeline.base.frame_pool import FramePool
from pipeline.depth.fast import FastDST
from pipeline.normals.fast import NearFieldFast, PlaneBatch

__all__ = ["CPUFramePipeline"]


class CPUFramePipeline:
    """Near-field normals + DST heights of many frames on ``threads`` threads.

    Parameters
    ----------
    solver : NearFieldFast
        The fast near-field path of the lights (its region, dark frame and flat field).
    depth : FastDST
        Of the frames' size and pitch.
    threads : int, optional
        Worker threads (None or 0: every core this process may use).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> L = rng.normal(size=(6, 8, 8, 3)); L[..., 2] = np.abs(L[..., 2]) + 2
    >>> frames = rng.integers(0, 255, size=(4, 6, 8, 8, 1), dtype=np.uint8)   # (K, P, H, W, C)
    >>> with CPUFramePipeline(NearFieldFast(L), FastDST((8, 8), 0.1), threads=2) as pipe:
    ...     res = pipe.run(frames)
    >>> res["height"].shape, res["planes"].normals.shape
    ((4, 8, 8), (4, 3, 8, 8))
    """

    def __init__(self, solver: NearFieldFast, depth: FastDST, threads: int | None = None):
        if tuple(depth.shape) != tuple(solver.shape):
            raise ValueError(f"CPUFramePipeline: the solver is for {solver.shape} frames, the integrator for "
                             f"{depth.shape}")
        self.solver = solver
        self.depth = depth
        self.pool = FramePool(None if not threads else threads)
        self.threads = self.pool.threads
        self._planes: PlaneBatch | None = None
        self._valid: np.ndarray | None = None

    def close(self) -> None:
        self.pool.close()

    def __enter__(self) -> CPUFramePipeline:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def planes(self, K: int) -> PlaneBatch:
        """The pipeline's normal planes for ``K`` frames (kept, so a stream of equal batches
        touches no new memory)."""
        if self._planes is None or len(self._planes) != K:
            self._planes = self.solver.batch_planes(K)
        return self._planes

    def normals(self, frames, out: PlaneBatch | None = None) -> PlaneBatch:
        """Phase 1 alone: the normal planes of ``frames (K, P, H, W, C)``."""
        f = np.asarray(frames)
        return self.solver.solve_batch(f, self.pool, out=self.planes(f.shape[0]) if out is None else out)

    def run(self, frames, out=None, planes: PlaneBatch | None = None) -> dict:
        """Heights of ``frames (K, P, H, W, C)`` uint8/uint16.

        Returns ``{"height": (K, H, W) float32 mm, "height_mask": (K, H, W) bool, "planes":
        PlaneBatch}``. ``out``: the ``(K, H, W)`` float32 array the heights go to (else a new
        one); ``planes``: where the normals go. Without ``planes``, the normals and the height
        mask are the pipeline's own buffers, overwritten by the next run (copy what you keep):
        a stream of equal batches touches no new memory.
        """
        p = self.normals(frames, planes)
        K = len(p)
        H, W = self.depth.shape
        height = np.empty((K, H, W), np.float32) if out is None else out
        if planes is not None:
            valid = np.empty((K, H, W), np.bool_)
        else:
            if self._valid is None or len(self._valid) != K:
                self._valid = np.empty((K, H, W), np.bool_)
            valid = self._valid
        self.depth.integrate_batch(p.normals, p.mask, self.pool, out=(height, valid))
        return {"height": height, "height_mask": valid, "planes": p}
