"""Results written behind the solve, made durable on a thread of their own."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

__all__ = ["ChunkWriter", "COMMIT_SECONDS"]

#: What is written is made durable (fsync) and recorded as done about this often (a kill loses at
#: most this much work; fsync more often cost the solving threads CPU time on a 2-core machine).
COMMIT_SECONDS = 2.0


class ChunkWriter:
    """Writes chunks on a thread of its own; on another, at most every :data:`COMMIT_SECONDS` (and at
    the end of a range), makes what is written durable (fsync) and records it, so the solving
    never waits for the disk to catch up, only for the page cache to take a chunk.

    A commit asked for while the last one is still syncing is not dropped: the syncing thread
    commits again, with what was written meanwhile, as soon as it is done, so a kill loses at most
    the work of one commit's time however slow the disk."""

    def __init__(self, files: dict):
        self.files = files
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="iristac-write")
        self.syncer = ThreadPoolExecutor(1, thread_name_prefix="iristac-sync")
        self.pending = self.syncing = None
        self.writers: dict = {}
        self.stats: dict[int, dict] = {}
        self.done = 0
        self.last_commit = time.monotonic()
        # What the writing and the syncing thread share: the frames written, their stats, and
        # whether a commit runs (and another was asked for meanwhile).
        self.lock = threading.Lock()
        self.sync_running = self.sync_wanted = False

    def begin(self, a: int, b: int) -> None:
        self.writers = {name: sf.writer(a, b) for name, sf in self.files.items()}
        self.stats, self.done = {}, a

    def write(self, at: int, arrays: dict, stats: dict) -> None:
        self._wait()  # one chunk in flight: memory stays one chunk's
        self.pending = self.pool.submit(self._write, at, arrays, stats)

    def _write(self, at: int, arrays: dict, stats: dict) -> None:
        for name, w in self.writers.items():
            w.write(at, arrays[name])
        with self.lock:
            self.stats.update(stats)
            self.done = at + len(next(iter(arrays["depth"].values())))
        if time.monotonic() - self.last_commit >= COMMIT_SECONDS:
            self._ask_commit()

    def _ask_commit(self) -> None:
        """Start a commit on the syncing thread, or, while one runs, have it commit once more."""
        with self.lock:
            if self.sync_running:
                self.sync_wanted = True
                return
            self.sync_running = True
        if self.syncing is not None:
            self.syncing.result()  # raise what the last commit raised (it has returned)
        self.last_commit = time.monotonic()
        self.syncing = self.syncer.submit(self._commit_latest)

    def _commit_latest(self) -> None:
        try:
            while True:
                with self.lock:
                    done, stats, self.stats, self.sync_wanted = self.done, self.stats, {}, False
                self._commit(done, stats)
                with self.lock:
                    if not self.sync_wanted:
                        self.sync_running = False
                        return
        except BaseException:
            with self.lock:
                self.sync_running = False
            raise

    def _commit(self, done: int, stats: dict) -> None:
        for w in self.writers.values():
            w.commit(done, stats)

    def _wait(self) -> None:
        if self.pending is not None:
            p, self.pending = self.pending, None
            p.result()

    def _wait_sync(self) -> None:
        if self.syncing is not None:
            s, self.syncing = self.syncing, None
            s.result()

    def end(self) -> None:
        self._wait()
        self._wait_sync()
        self._commit(self.done, self.stats)
        self.stats = {}
        for w in self.writers.values():
            w.close()
        self.writers = {}

    def __enter__(self) -> ChunkWriter:
        return self

    def __exit__(self, *exc) -> None:
        try:
            self._wait()
            self._wait_sync()
        finally:
            for w in self.writers.values():
                w.close()
            self.pool.shutdown()
            self.syncer.shutdown()
