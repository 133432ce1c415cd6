"""Process many recordings with one task: serially, on a local process pool, or on a Dask cluster.

One bad recording is reported and skipped, never stops the rest; results come back in the
order of the inputs whatever order the workers finish in, so a parallel run equals a serial
one. The task is any picklable callable ``task(recording: str) -> dict`` (a module-level
function or a :func:`functools.partial` of one); what it returns must be JSON-able.

Examples
--------
>>> from functools import partial
>>> results = run_batch(["a", "bb", "ccc"], len)
>>> [r.result for r in results], all(r.ok for r in results)
([1, 2, 3], True)
"""

from __future__ import annotations

import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any, Callable, Sequence

from pipeline.base.errors import UserError
from pipeline.results.report import format_number

__all__ = ["BatchItem", "run_batch", "map_tasks", "progress_bar", "format_summary", "error_message"]


@dataclass
class BatchItem:
    """The outcome of one recording."""

    recording: str
    ok: bool
    seconds: float
    result: Any = None
    error: str | None = None
    worker: str = ""
    #: How the frames were solved: ``fast``, ``eager``, or ``cached`` (read from the store).
    method: str = ""
    #: Frames solved, and the seconds from the first frame read to the last result on disk
    #: (planning and start-up, in ``seconds``, excluded; a cluster's wall time shared by frames).
    frames_solved: int = 0
    solve_seconds: float = 0.0

    def to_json(self) -> dict:
        return {"recording": self.recording, "ok": self.ok, "seconds": round(self.seconds, 4),
                "result": self.result, "error": self.error, "worker": self.worker, "method": self.method}


def _guarded(task: Callable[[str], Any], recording: str) -> BatchItem:
    """Run ``task`` on one recording; turn any exception into a failed item."""
    import os
    import socket

    t0 = time.perf_counter()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        result = task(recording)
        return BatchItem(recording, True, time.perf_counter() - t0, result, None, worker)
    except Exception as exc:  # noqa: BLE001 - one bad recording must not stop the batch
        return BatchItem(recording, False, time.perf_counter() - t0, None, error_message(exc), worker)


def run_batch(recordings: Sequence[str], task: Callable[[str], Any], *, workers: int = 1,
              scheduler: str | None = None, progress: bool = False,
              connect_timeout: float = 10.0) -> list[BatchItem]:
    """Apply ``task`` to every recording and collect the outcomes in input order.

    Parameters
    ----------
    recordings : sequence of str
        Paths (or any strings the task understands).
    task : callable
        ``task(recording) -> JSON-able``; must be picklable when ``workers > 1`` or with a
        scheduler.
    workers : int
        Local processes (1 = in this process).
    scheduler : str, optional
        Address of a Dask distributed scheduler (``tcp://host:8786``); the work is spread
        over its workers instead of a local pool.
    progress : bool
        Show a progress bar on stderr.
    connect_timeout : float
        Seconds to wait for the Dask scheduler to answer.
    """
    recordings = [str(r) for r in recordings]
    if workers < 1:
        raise UserError(f"--workers must be at least 1, got {workers}")
    bar = _bar(len(recordings), progress)
    try:
        if scheduler:
            return _run_dask(recordings, task, scheduler, bar, connect_timeout)
        if workers == 1 or len(recordings) <= 1:
            out = []
            for r in recordings:
                out.append(_guarded(task, r))
                bar.update(1)
            return out
        # spawn: torch and HDF5 are not fork-safe once initialised in the parent.
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
            futures = [pool.submit(_guarded, task, r) for r in recordings]
            out = []
            for f in futures:
                out.append(f.result())
                bar.update(1)
            return out
    finally:
        bar.close()


def _run_dask(recordings, task, scheduler, bar, connect_timeout) -> list[BatchItem]:
    client = _dask_client(scheduler, connect_timeout)
    try:
        futures = client.map(_guarded, [task] * len(recordings), recordings, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        out: list[BatchItem | None] = [None] * len(recordings)
        from distributed import as_completed

        for fut in as_completed(futures):
            out[index[fut.key]] = fut.result()
            bar.update(1)
        return out  # type: ignore[return-value]
    finally:
        client.close()


def map_tasks(fn: Callable, tasks: Sequence[tuple], *, workers: int = 1, scheduler: str | None = None,
              connect_timeout: float = 10.0, on_done: Callable[[int], None] | None = None) -> list[tuple[bool, Any]]:
    """``fn(*task)`` for every task: in this process, on ``workers`` local processes, or on a Dask
    cluster (``scheduler``); ``[(True, result) or (False, error message)]`` in task order (a failed
    task never stops the others). ``on_done(index)`` as each finishes. ``fn`` and the tasks must be
    picklable for a pool or a cluster.

    >>> [(ok, value if ok else value.split(" (at")[0]) for ok, value in map_tasks(divmod, [(7, 2), (1, 0)])]
    [(True, (3, 1)), (False, 'ZeroDivisionError: integer division or modulo by zero')]
    """
    if workers < 1:
        raise UserError(f"--workers must be at least 1, got {workers}")
    out: list[tuple[bool, Any]] = [(False, "not run")] * len(tasks)
    done = on_done or (lambda i: None)
    if scheduler:
        return _map_dask(fn, tasks, scheduler, connect_timeout, done)
    if workers == 1 or len(tasks) <= 1:
        for i, t in enumerate(tasks):
            out[i] = _call_guarded(fn, t)
            done(i)
        return out
    # spawn: torch and HDF5 are not fork-safe once initialised in the parent.
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(_call_guarded, fn, t): i for i, t in enumerate(tasks)}
        from concurrent.futures import as_completed

        for f in as_completed(futures):
            out[futures[f]] = f.result()
            done(futures[f])
    return out


def _call_guarded(fn: Callable, task: tuple) -> tuple[bool, Any]:
    try:
        return True, fn(*task)
    except Exception as exc:  # noqa: BLE001 - reported in its result
        return False, error_message(exc)


def error_message(exc: BaseException) -> str:
    """One line for a failed recording or task: a UserError's message, else the exception's type,
    message and where it was raised."""
    msg = str(exc) or type(exc).__name__
    if not isinstance(exc, UserError):
        last = traceback.extract_tb(exc.__traceback__)[-1:]
        where = f" (at {last[0].filename}:{last[0].lineno})" if last else ""
        msg = f"{type(exc).__name__}: {msg}{where}"
    return msg


def _map_dask(fn, tasks, scheduler, connect_timeout, done) -> list[tuple[bool, Any]]:
    client = _dask_client(scheduler, connect_timeout)
    try:
        from distributed import as_completed

        futures = [client.submit(_call_guarded, fn, t, pure=False) for t in tasks]
        index = {f.key: i for i, f in enumerate(futures)}
        out: list[tuple[bool, Any]] = [(False, "not run")] * len(tasks)
        for fut in as_completed(futures):
            out[index[fut.key]] = fut.result()
            done(index[fut.key])
        return out
    finally:
        client.close()


def _dask_client(scheduler: str, connect_timeout: float):
    try:
        from distributed import Client
    except ImportError as exc:  # pragma: no cover - dask[distributed] is a dependency
        raise UserError("--scheduler needs dask.distributed (pip install 'dask[distributed]')") from exc
    import dask

    try:
        # The comm-level connect timeout governs retries on a refused connection.
        with dask.config.set({"distributed.comm.timeouts.connect": f"{connect_timeout}s"}):
            return Client(scheduler, timeout=f"{connect_timeout}s")
    except OSError as exc:
        raise UserError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there ({exc})") from None


def progress_bar(total: int, enabled: bool, *, unit: str = "rec", desc: str = "batch"):
    """A tqdm bar on stderr (rate and time left), or one that draws nothing."""
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, desc=desc, unit_scale=False, smoothing=0.1)


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _bar(total: int, enabled: bool):
    return progress_bar(total, enabled)


def format_summary(items: Sequence[BatchItem], columns: Sequence[str] = ()) -> str:
    """A plain-text table: one row per recording, then totals.

    ``columns`` picks keys of each item's result dict to show.
    """
    name_w = max([len("recording")] + [len(i.recording) for i in items])
    head = f"{'recording':<{name_w}}  {'status':<6} {'seconds':>8}" + "".join(f"  {c:>14}" for c in columns)
    lines = [head, "-" * len(head)]
    for i in items:
        row = f"{i.recording:<{name_w}}  {'ok' if i.ok else 'FAILED':<6} {i.seconds:>8.3f}"
        for c in columns:
            v = i.result.get(c) if i.ok and isinstance(i.result, dict) else None
            row += f"  {format_number(v, '-'):>14}"
        lines.append(row)
        if not i.ok:
            lines.append(f"{'':<{name_w}}  -> {i.error}")
    ok = sum(i.ok for i in items)
    lines.append(f"{ok} of {len(items)} recordings processed, {len(items) - ok} failed, "
                 f"{sum(i.seconds for i in items):.2f} s of work")
    return "\n".join(lines)

