"""``--record FILE.h5``: a live recording that is valid HDF5 at every moment, a kill included.

HDF5 is not crash-safe: a writer killed between its metadata writes leaves a file the
library cannot open, and SWMR files killed mid-write need ``h5clear`` before they open. So
the recording is append-only files plus an atomically replaced index:

- results are buffered and written, every ``segment_results`` results or ``segment_seconds``
  seconds, as one complete segment file ``FILE.h5.parts/segment-NNNNNN.h5`` (a temporary
  name, fsynced, renamed: a segment is there whole or not at all);
- after each segment, ``FILE.h5`` itself is rewritten (again temporary name, fsync, rename)
  as a small file of *virtual datasets* over every complete segment (schema ``recording``,
  ``complete = false``). A reader (``read_record(FILE.h5, "recording")``, h5py) sees one
  ``frames``, ``normals`` ... dataset spanning all segments; a kill at any instant leaves
  the previous index or the new one, both valid, losing at most the results not yet in a
  segment;
- :meth:`LiveRecorder.close` writes the last segment and consolidates everything into one
  self-contained ``FILE.h5`` (``complete = true``, through :func:`pipeline.base.store.write_record`)
  and removes the parts.

``tests/pipeline/live/test_live_record.py`` kills a real recording process with SIGKILL and
opens what it left.
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from pathlib import Path

import numpy as np

from pipeline.base.store import fsync_dir, fsync_file  # the store's own durable-write steps

__all__ = ["LiveRecorder", "read_recording"]

#: Datasets of one result (``contact``, the contact mask, with ``contact=True``).
FIELDS = ("frames", "normals", "mask", "height", "timestamp", "wall", "latency_ms", "index", "dropped")


class LiveRecorder:
    """Record live results to ``path`` (see the module docstring).

    Parameters
    ----------
    path : path-like
        ``FILE.h5``; ``FILE.h5.parts/`` beside it holds the segments while recording.
    meta : dict
        Attributes (``mode``, ``solver``, ``source``, ``mm_per_px`` ...).
    segment_results, segment_seconds : int, float
        A segment is written when either is reached (what a kill can lose at most).
    contact : bool
        Also record each result's contact mask (``contact (K, H, W)`` bool).
    """

    def __init__(self, path, meta: dict, *, segment_results: int = 16, segment_seconds: float = 0.5,
                 contact: bool = False):
        self.path = Path(path)
        self.parts = self.path.with_name(self.path.name + ".parts")
        if self.parts.exists():
            shutil.rmtree(self.parts)  # an earlier recording's leftovers under this name
        self.parts.mkdir(parents=True)
        self.meta = dict(meta)
        self.segment_results = int(segment_results)
        self.segment_seconds = float(segment_seconds)
        self.fields = FIELDS + (("contact",) if contact else ())
        self._buf: dict[str, list] = {k: [] for k in self.fields}
        self._segments: list[tuple[str, int]] = []  # (file name, results)
        self._shapes: dict[str, tuple] = {}
        self._dtypes: dict[str, np.dtype] = {}
        self._since = time.monotonic()
        self._lock = threading.Lock()
        self.results = 0
        self.dropped_total = 0
        self.closed = False
        self._write_index()

    def add(self, *, frames, normals, mask, height, timestamp: float, latency_ms: float, index: int,
            dropped: int, wall: float | None = None, contact=None) -> None:
        """Buffer one result (with ``contact``, its contact mask ``(H, W)``, when recording them);
        write a segment when one is due."""
        row = {"frames": np.asarray(frames), "normals": np.asarray(normals, np.float32),
               "mask": np.asarray(mask, bool), "height": np.asarray(height, np.float32),
               "timestamp": np.float64(timestamp), "wall": np.float64(time.time() if wall is None else wall),
               "latency_ms": np.float32(latency_ms), "index": np.int64(index), "dropped": np.int64(dropped)}
        if "contact" in self.fields:
            if contact is None:
                raise ValueError(f"{self.path}: this recording records contact masks; add(contact=...) is missing")
            row["contact"] = np.asarray(contact, bool)
        with self._lock:
            if self.closed:
                raise RuntimeError(f"{self.path}: the recording is closed")
            for k, v in row.items():
                self._buf[k].append(v)
            self.dropped_total = int(dropped)
            due = (len(self._buf["frames"]) >= self.segment_results
                   or time.monotonic() - self._since >= self.segment_seconds)
            if due:
                self._flush_segment()

    def _flush_segment(self) -> None:
        from pipeline.base.frame_codec import h5py_with_filters

        h5py = h5py_with_filters()

        n = len(self._buf["frames"])
        self._since = time.monotonic()
        if n == 0:
            return
        arrays = {k: np.stack(v) for k, v in self._buf.items()}
        for k, a in arrays.items():
            self._shapes.setdefault(k, a.shape[1:])
            self._dtypes.setdefault(k, a.dtype)
        name = f"segment-{len(self._segments):06d}.h5"
        final = self.parts / name
        tmp = self.parts / f".{name}.tmp"
        with h5py.File(tmp, "w") as f:
            for k, a in arrays.items():
                f.create_dataset(k, data=a)
        fsync_file(tmp)
        os.replace(tmp, final)
        self._segments.append((name, n))
        self.results += n
        self._buf = {k: [] for k in self.fields}
        self._write_index()

    def _attrs(self, complete: bool) -> dict:
        return {**self.meta, "complete": bool(complete), "results": int(self.results),
                "dropped_total": int(self.dropped_total)}

    def _write_index(self) -> None:
        """Atomically replace FILE.h5 with virtual datasets over the complete segments."""
        from pipeline.base.frame_codec import h5py_with_filters
        from pipeline.base.store import provenance_attrs

        h5py = h5py_with_filters()

        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp.h5")
        with h5py.File(tmp, "w", libver="latest") as f:
            for k in self.fields:
                if not self._segments:  # nothing recorded yet: empty datasets of unknown frame size
                    shape, dt = {"frames": (0, 0, 0, 0), "normals": (0, 0, 3), "mask": (0, 0),
                                 "height": (0, 0), "contact": (0, 0)}.get(k, ()), _EMPTY_DTYPES[k]
                    f.create_dataset(k, shape=(0,) + shape, dtype=dt)
                    continue
                shape, dt = self._shapes[k], self._dtypes[k]
                layout = h5py.VirtualLayout(shape=(self.results,) + shape, dtype=dt)
                at = 0
                for name, n in self._segments:
                    # Relative source: resolved beside FILE.h5 wherever it is opened from.
                    layout[at:at + n] = h5py.VirtualSource(f"{self.parts.name}/{name}", k, shape=(n,) + shape)
                    at += n
                f.create_virtual_dataset(k, layout)
            json_keys = []
            for k, v in self._attrs(False).items():
                if isinstance(v, (bool, int, float, str, np.generic)):
                    f.attrs[k] = v
                else:
                    f.attrs[k] = json.dumps(v)
                    json_keys.append(k)
            for k, v in provenance_attrs("recording").items():
                f.attrs[k] = v
            f.attrs["iristac_json_attrs"] = json.dumps(sorted(json_keys))
        fsync_file(tmp)
        os.replace(tmp, self.path)
        fsync_dir(self.path.parent)

    def close(self, stopped: str = "", dropped: int | None = None) -> Path:
        """Write what is buffered, consolidate into one self-contained file, remove the parts;
        ``stopped`` says why the stream ended, ``dropped`` the final count of dropped samples."""
        from pipeline.base.store import Record, read_record, write_record

        with self._lock:
            if self.closed:
                return self.path
            self._flush_segment()
            self.closed = True
            if dropped is not None:
                self.dropped_total = int(dropped)
            rec = read_record(self.path, schema="recording")  # through the virtual datasets
            meta = self._attrs(True)
            if stopped:
                meta["stopped"] = stopped
            write_record(self.path, Record("recording", rec.data, meta))
            shutil.rmtree(self.parts, ignore_errors=True)
        return self.path


_EMPTY_DTYPES = {"frames": np.uint8, "normals": np.float32, "mask": np.bool_, "height": np.float32,
                 "timestamp": np.float64, "wall": np.float64, "latency_ms": np.float32, "index": np.int64,
                 "dropped": np.int64, "contact": np.bool_}


def read_recording(path):
    """The ``recording`` Record of a live recording (complete, or what a killed one left)."""
    from pipeline.base.store import read_record

    return read_record(path, schema="recording")
