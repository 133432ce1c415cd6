"""Frame-level parallelism: many frames at once on the threads of one process.

A 320 x 240 frame is too small to split well across many cores (its per-pixel kernels are
memory-bound and each split costs a fork and a join: the near-field path gained 2.2-2.4x on 16
cores that way). Throughput work (``iristac batch``, ``iristac bench live``'s frames rows)
instead hands threads many frames at once. Two ways:

- :meth:`FramePool.split`: ``fn(start, stop)`` over a few contiguous parts of a range (pixels
  or frames of a whole batch), each part one call into compiled code that releases the GIL:
  Python and its lock are entered a few times per thread and batch, not per frame (the
  near-field batch path, :class:`pipeline.frame_pipeline.cpu_batch.CPUFramePipeline`);
- :meth:`FramePool.map`: one Python call per item, in input order (the depth stage's other
  integrators, one contact instance each).

Examples
--------
>>> with FramePool(2) as pool:
...     pool.map(lambda x: x * x, range(5))
[0, 1, 4, 9, 16]
>>> with FramePool(2) as pool:
...     pool.split(lambda a, b: (a, b), 10, parts=3)
[(0, 4), (4, 7), (7, 10)]
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

    def split(self, fn: Callable[[int, int], R], n: int, *, parts: int | None = None, multiple: int = 1) -> list[R]:
        """``[fn(a, b) for (a, b) in parts of range(n)]``: ``parts`` (default: the threads)
        contiguous parts as equal as whole units of ``multiple`` allow (sizes differ by at most
        one unit; the last part ends at ``n``), run on the threads (in the calling thread with
        one); results in order, the first error raised."""
        if n < 0 or multiple < 1:
            raise ValueError(f"FramePool.split: n >= 0 and multiple >= 1 expected, got n={n}, multiple={multiple}")
        units = -(-n // multiple)
        parts = max(1, min(units, self.threads if parts is None else int(parts)))
        size, extra = divmod(units, parts)
        bounds, a = [], 0
        for i in range(parts):
            b = min(n, a + (size + (i < extra)) * multiple)
            if b > a:
                bounds.append((a, b))
            a = b
        if self._pool is None or len(bounds) < 2:
            return [fn(a, b) for a, b in bounds]
        futures = [self._pool.submit(fn, a, b) for a, b in bounds]
        return [f.result() for f in futures]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __enter__(self) -> FramePool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
