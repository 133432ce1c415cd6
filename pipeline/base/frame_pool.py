"""Frame-level parallelism: many frames at once, one per thread, results in input order.

A 320 x 240 frame is too small to split well across many cores (its per-pixel kernels are
memory-bound and each split costs a fork and a join: the near-field path gained 2.2-2.4x on 16
cores that way). Throughput work (``iristac batch``, ``iristac bench live``'s throughput rows)
instead gives each thread whole frames, each solved and integrated on one thread by the same
kernels: the Numba kernels, OpenCV and ``scipy.fft`` release the GIL, so threads of one process
scale with the cores while the per-frame kernels keep their one-frame latency.

Examples
--------
>>> with FramePool(2) as pool:
...     pool.map(lambda x: x * x, range(5))
[0, 1, 4, 9, 16]
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

__all__ = ["FramePool", "default_threads"]

T = TypeVar("T")
R = TypeVar("R")


def default_threads() -> int:
    """The cores this process may run on (its CPU affinity where the platform says)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - platforms without affinity
        return max(1, os.cpu_count() or 1)


class FramePool:
    """``threads`` worker threads mapping a per-frame function over frames, in order.

    Parameters
    ----------
    threads : int, optional
        Worker threads (None: :func:`default_threads`); 1 runs in the calling thread.
    """

    def __init__(self, threads: int | None = None):
        self.threads = default_threads() if threads is None else int(threads)
        if self.threads < 1:
            raise ValueError(f"FramePool: threads must be at least 1, got {threads}")
        self._pool = (ThreadPoolExecutor(self.threads, thread_name_prefix="iristac-frames")
                      if self.threads > 1 else None)

    def map(self, fn: Callable[[T], R], frames: Iterable[T]) -> list[R]:
        """``[fn(f) for f in frames]``, ``threads`` frames at a time; the first error is raised."""
        if self._pool is None:
            return [fn(f) for f in frames]
        return list(self._pool.map(fn, frames))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __enter__(self) -> FramePool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
