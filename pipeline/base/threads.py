"""The one thread-limit helper: run a block on fewer torch and BLAS threads, restoring them after.

On a small shared CPU, torch's and OpenBLAS's default of one thread per core collapses when
other processes compete for the cores: the idle workers spin waiting for a core, and a
single thread is then many times faster (measured: a 150-step MLP fit 17 s with two torch
threads, 0.5 s with one; a near-field calibration fit 1.05 s with two BLAS threads, 0.17 s
with one; one LED traced 0.65 s single-threaded vs 3-30 s with two under load). Every place
that needs fewer threads uses :func:`limit_threads`.

Examples
--------
>>> import torch
>>> before = torch.get_num_threads()
>>> with limit_threads(torch=1):
...     torch.get_num_threads()
1
>>> torch.get_num_threads() == before
True
"""

from __future__ import annotations

import contextlib
from typing import Iterator

__all__ = ["limit_threads"]


@contextlib.contextmanager
def limit_threads(torch: int | None = None, blas: int | None = None) -> Iterator[None]:
    """Context manager: at most ``torch`` intra-op torch threads and ``blas`` BLAS threads.

    Parameters
    ----------
    torch : int, optional
        Torch intra-op threads inside the block (``None`` leaves torch alone; torch is then
        not even imported).
    blas : int, optional
        BLAS threads of numpy/scipy inside the block, by :mod:`threadpoolctl` (``None``
        leaves them alone).

    The previous counts are restored when the block ends, also on an exception.
    """
    with contextlib.ExitStack() as stack:
        if torch is not None:
            import torch as _torch

            old = _torch.get_num_threads()
            if old != int(torch):
                _torch.set_num_threads(int(torch))
                stack.callback(_restore_torch, old)
        if blas is not None:
            from threadpoolctl import threadpool_limits

            stack.enter_context(threadpool_limits(limits=int(blas), user_api="blas"))
        yield


def _restore_torch(n: int) -> None:
    import torch as _torch

    if _torch.get_num_threads() != n:
        _torch.set_num_threads(n)
