"""Store files written a run of frames at a time, which a kill at any moment leaves resumable.

A recording's results are too large to hold in memory, so they are written as they come. HDF5
is not crash-safe (a writer killed between two of its metadata writes leaves a file the
library cannot open), so a streamed file is laid out whole before its first frame:

- every per-frame dataset (first axis: the ``K`` frames) is chunked in runs of whole frames,
  unfiltered, and its chunks are allocated when the file is created (no fill value written:
  the file is sparse until written); its metadata is then final, and the file is closed;
- frames are written by file offset (``os.pwrite`` on the bytes of their chunks, whose places
  are read from HDF5 once through public h5py calls, ``DatasetID.chunk_iter``; the mirror of
  :class:`pipeline.base.h5frames.H5Frames`, which reads such files the same way), so no HDF5
  metadata changes while frames arrive, and several threads, processes or machines (a Dask
  cluster on a shared folder) can write disjoint frame ranges of one file at once;
- after a run of frames is on disk (``fsync``), a small progress file beside it says so
  (written to a temporary name and renamed): what it claims is there;
- :meth:`StreamedFile.finish` sets the attributes that summarise every frame, validates the
  file against its schema, fsyncs it and renames it to its final name.

The partial file is ``.<name>.partial.h5`` beside the final one, its progress files
``.<name>.progress-<start>.json`` (one per writer of a frame range). A killed run leaves them;
the next run with the same key (:meth:`StreamedFile.open` finds them) writes only the frames no
progress file claims. The store lists them as ``partial`` entries (``iristac cache ls``).

Examples
--------
>>> import tempfile, os
>>> d = tempfile.mkdtemp()
>>> final = os.path.join(d, "out.h5")
>>> sf = StreamedFile.open(final, "depth", 4, {"height": ((3, 5), "float32"), "mask": ((3, 5), "bool")},
...                        meta={"integrator": "dst", "mm_per_px": 0.1})
>>> sf.missing()
[(0, 4)]
>>> with sf.writer(0, 2) as w:
...     w.write(0, {"height": np.ones((2, 3, 5), np.float32), "mask": np.ones((2, 3, 5), bool)})
...     w.commit(2)
>>> StreamedFile.open(final, "depth", 4, {"height": ((3, 5), "float32"), "mask": ((3, 5), "bool")},
...                   meta={"integrator": "dst", "mm_per_px": 0.1}).missing()   # a new process: resumes
[(2, 4)]
>>> with sf.writer(2, 4) as w:
...     w.write(2, {"height": np.zeros((2, 3, 5), np.float32), "mask": np.zeros((2, 3, 5), bool)})
...     w.commit(4)
>>> from pipeline.base.store import read_record
>>> rec = read_record(sf.finish({"valid_fraction": 0.5}))
>>> rec.data["height"][:, 0, 0].tolist(), rec.meta["valid_fraction"]
([1.0, 1.0, 0.0, 0.0], 0.5)
"""

from __future__ import annotations

import json
import logging
import os
import threading
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from pipeline.base.errors import UserError

__all__ = ["StreamedFile", "RangeWriter", "partial_path", "progress_files", "merge_ranges", "CHUNK_BYTES"]

_log = logging.getLogger("iristac")

#: A chunk holds as many whole frames as fit in this many bytes (at least one): a 320 x 240
#: float32 height map is one frame a chunk, a per-frame scalar thousands.
CHUNK_BYTES = 1 << 20

#: The progress files' format version (a file of another is ignored: its frames are written again).
_PROGRESS_VERSION = 2




def partial_path(final: str | os.PathLike) -> Path:
    """Where the partial file of ``final`` lives while it is written."""
    final = Path(final)
    return final.with_name(f".{final.stem}.partial.h5")


def progress_files(final: str | os.PathLike) -> list[Path]:
    """The progress files of ``final``'s partial file (one per frame range written)."""
    final = Path(final)
    return sorted(final.parent.glob(f".{final.stem}.progress-*.json"))


def merge_ranges(ranges: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
    """Sorted, disjoint ``[start, stop)`` ranges covering the same frames.

    >>> merge_ranges([(4, 6), (0, 2), (2, 3), (5, 9)])
    [(0, 3), (4, 9)]
    """
    out: list[tuple[int, int]] = []
    for a, b in sorted((int(a), int(b)) for a, b in ranges if b > a):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def _layout(frames: int, datasets: Mapping[str, tuple]) -> dict[str, dict]:
    """Name -> ``{"shape", "dtype", "chunk"}`` (the chunk in frames) of the per-frame datasets."""
    out = {}
    for name, (frame_shape, dtype) in datasets.items():
        dt = np.dtype(dtype)
        frame_shape = tuple(int(s) for s in frame_shape)
        frame_bytes = max(1, int(np.prod(frame_shape, dtype=np.int64)) * dt.itemsize)
        chunk = max(1, min(max(frames, 1), CHUNK_BYTES // frame_bytes))
        out[name] = {"shape": [int(frames), *frame_shape], "dtype": dt.str, "chunk": int(chunk)}
    return out


class StreamedFile:
    """One store file written a run of frames at a time (see the module docstring).

    Use :meth:`open`, not the constructor.

    Attributes
    ----------
    final : Path
        Where the finished file goes.
    partial : Path
        The file being written.
    frames : int
        ``K``, the frames of every per-frame dataset.
    layout : dict
        Per-frame dataset name -> ``{"shape", "dtype", "chunk"}``.
    """

    def __init__(self, final: Path, schema: str, frames: int, layout: dict, provenance: dict):
        self.final, self.schema, self.frames, self.layout = final, schema, int(frames), layout
        self.partial = partial_path(final)
        self.provenance = provenance

    # -- creation and resumption -----------------------------------------------------------
    @classmethod
    def open(cls, final: str | os.PathLike, schema: str, frames: int, datasets: Mapping[str, tuple], *,
             static: Mapping[str, Any] | None = None, meta: Mapping[str, Any] | None = None, key=None,
             resume: bool = True) -> StreamedFile:
        """The partial file of ``final``: resumed when one with the same key and layout is there
        (and ``resume``), else created anew (an older partial file, with its progress, removed).

        Parameters
        ----------
        final : path
            The finished file's path (a store entry's, or any).
        schema : str
            Its schema (:mod:`data_schemas`); checked in :meth:`finish`.
        frames : int
            ``K``.
        datasets : mapping
            Per-frame dataset name -> ``(frame shape, dtype)``: the file holds ``(K, *frame shape)``.
        static : mapping, optional
            Datasets written whole at creation (name -> array), through the store's writer.
        meta : mapping, optional
            Attributes known at creation; :meth:`finish` adds the rest.
        key : StageKey, optional
            The store key (recorded in the provenance attributes, and what a resumed file must match).
        """
        from pipeline.base.store import provenance_attrs

        final = Path(final)
        layout = _layout(frames, datasets)
        provenance = provenance_attrs(schema, key)
        sf = cls(final, schema, frames, layout, provenance)
        if resume and sf._resumable():
            return sf
        sf.discard()
        final.parent.mkdir(parents=True, exist_ok=True)
        sf._create(static or {}, meta or {})
        return sf

    def _resumable(self) -> bool:
        """Whether the partial file there is this one (same key, schema and layout) and readable."""
        import h5py

        if not self.partial.is_file():
            return False
        try:
            with h5py.File(self.partial, "r") as f:
                ok = (str(f.attrs.get("iristac_key", "")) == str(self.provenance["iristac_key"])
                      and str(f.attrs.get("iristac_schema", "")) == self.schema
                      and str(f.attrs.get("iristac_stream_layout", "")) == json.dumps(self.layout, sort_keys=True))
        except Exception as exc:  # noqa: BLE001 - a damaged partial file is written again, said once
            _log.warning("%s: partial file unreadable (%s); writing it again", self.partial, exc)
            return False
        return ok

    def _create(self, static: Mapping[str, Any], meta: Mapping[str, Any]) -> None:
        import h5py

        from pipeline.base.store import create_dataset, write_attrs

        tmp = self.partial.with_name(self.partial.name + f".{os.getpid()}.tmp")
        with h5py.File(tmp, "w", libver="latest") as f:
            for name, info in self.layout.items():
                dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
                dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)  # every chunk placed now: metadata final
                chunks = (info["chunk"], *info["shape"][1:]) if all(info["shape"][1:]) else True
                f.create_dataset(name, shape=tuple(info["shape"]), dtype=np.dtype(info["dtype"]), chunks=chunks,
                                 dcpl=dcpl, fill_time="never")
            for name, value in static.items():
                create_dataset(f, name, value)
            write_attrs(f, {**meta, "stream_datasets": sorted(self.layout)}, self.provenance)
            f.attrs["iristac_stream_layout"] = json.dumps(self.layout, sort_keys=True)
        from pipeline.base.store import fsync_dir, fsync_file

        fsync_file(tmp)
        os.replace(tmp, self.partial)
        fsync_dir(self.partial.parent)

    def discard(self) -> None:
        """Remove the partial file and its progress files (a fresh start)."""
        for p in progress_files(self.final):
            p.unlink(missing_ok=True)
        self.partial.unlink(missing_ok=True)

    # -- progress ----------------------------------------------------------------------------
    def _progress(self) -> list[dict]:
        out = []
        for p in progress_files(self.final):
            try:
                d = json.loads(p.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                continue  # half a progress file cannot exist (renamed into place); a foreign one is ignored
            if d.get("version") == _PROGRESS_VERSION and d.get("key") == self.provenance["iristac_key"]:
                out.append(d)
        return out

    def done(self) -> list[tuple[int, int]]:
        """The frame ranges on disk (merged)."""
        return merge_ranges((d["start"], d["done"]) for d in self._progress())

    def missing(self) -> list[tuple[int, int]]:
        """The frame ranges still to write, in order."""
        out, at = [], 0
        for a, b in self.done():
            if a > at:
                out.append((at, a))
            at = max(at, b)
        if at < self.frames:
            out.append((at, self.frames))
        return out

    def stats(self) -> dict[int, dict]:
        """Per-frame values the writers recorded beside their frames (:meth:`RangeWriter.commit`):
        frame -> dict (a frame written twice keeps its last)."""
        out: dict[int, dict] = {}
        for d in self._progress():
            for k, v in d.get("stats", {}).items():
                if int(k) < d["done"]:
                    out[int(k)] = v
        return out

    def writer(self, start: int, stop: int) -> RangeWriter:
        """A writer of frames ``start:stop`` (only its frames; a context manager)."""
        if not (0 <= start <= stop <= self.frames):
            raise ValueError(f"{self.final}: frames {start}:{stop} of {self.frames}")
        return RangeWriter(self, start, stop)

    # -- finishing ---------------------------------------------------------------------------
    def finish(self, meta: Mapping[str, Any] | None = None) -> Path:
        """Every frame written: set ``meta``'s attributes, validate, fsync, rename into place,
        remove the progress files. Returns the final path.

        Raises
        ------
        UserError
            Frames are missing (naming them), or the file does not match its schema.
        """
        import h5py

        import data_schemas
        from pipeline.base.store import (
            DIGEST_ATTR,
            StoreError,
            crc_digest,
            describe_file,
            fsync_dir,
            fsync_file,
            write_attrs,
        )

        gaps = self.missing()
        if gaps:
            raise UserError(f"{self.final}: frames {', '.join(f'{a}:{b}' for a, b in gaps)} of {self.frames} not "
                            f"written yet; nothing renamed")
        crcs = self.stats()
        digest = crc_digest([int(crcs.get(k, {}).get("crc", 0)) for k in range(self.frames)])
        with h5py.File(self.partial, "r+") as f:
            write_attrs(f, {**(meta or {}), DIGEST_ATTR: digest}, None, merge=True)
            del f.attrs["iristac_stream_layout"]
        description, _ = describe_file(self.partial)
        try:
            data_schemas.validate_description(self.schema, description, str(self.final))
        except data_schemas.SchemaError as exc:
            raise StoreError(self.final, f"streamed file does not match its schema: {exc}") from None
        fsync_file(self.partial)
        os.replace(self.partial, self.final)
        for p in progress_files(self.final):
            p.unlink(missing_ok=True)
        fsync_dir(self.final.parent)
        return self.final


class RangeWriter:
    """Writes frames ``start:stop`` of a :class:`StreamedFile` by file offset; :meth:`commit`
    makes what is written durable and says so in this range's progress file."""

    def __init__(self, sf: StreamedFile, start: int, stop: int):
        import h5py

        self.sf, self.start, self.stop = sf, int(start), int(stop)
        self.progress = sf.final.with_name(f".{sf.final.stem}.progress-{self.start:010d}.json")
        self._stats: dict[str, Any] = {}
        self._lock = threading.Lock()  # the writing thread adds CRCs while a committing one records
        self._places: dict[str, tuple[np.ndarray, int, int, np.dtype]] = {}
        with h5py.File(sf.partial, "r") as f:
            for name, info in sf.layout.items():
                ds = f[name]
                frame_bytes = int(np.prod(info["shape"][1:], dtype=np.int64)) * np.dtype(info["dtype"]).itemsize
                offsets = np.zeros(-(-info["shape"][0] // info["chunk"]), np.int64)
                if frame_bytes and info["shape"][0]:
                    def place(ci, offsets=offsets, chunk=info["chunk"]):
                        offsets[ci.chunk_offset[0] // chunk] = ci.byte_offset

                    ds.id.chunk_iter(place)
                self._places[name] = (offsets, info["chunk"], frame_bytes, np.dtype(info["dtype"]))
        self._fd = os.open(sf.partial, os.O_WRONLY)

    def write(self, at: int, arrays: Mapping[str, np.ndarray]) -> None:
        """Frames ``at : at + n`` of every per-frame dataset (``arrays[name]`` of shape ``(n, *frame
        shape)``; each name of the layout, in its dtype). Each frame's checksum over its datasets is
        kept for the file's :data:`pipeline.base.store.DIGEST_ATTR` (what guards unfiltered data against a flipped bit)."""
        self._crcs(at, arrays)
        n = None
        for name, (offsets, chunk, frame_bytes, dt) in self._places.items():
            a = arrays[name]
            if a.dtype != dt or tuple(a.shape[1:]) != tuple(self.sf.layout[name]["shape"][1:]):
                raise ValueError(f"{self.sf.final}: {name} must be (n, {self.sf.layout[name]['shape'][1:]}) {dt}, got "
                                 f"{a.shape} {a.dtype}")
            n = len(a) if n is None else n
            if len(a) != n or not (self.start <= at and at + n <= self.stop):
                raise ValueError(f"{self.sf.final}: frames {at}:{at + len(a)} outside this writer's "
                                 f"{self.start}:{self.stop}")
            buf = memoryview(np.ascontiguousarray(a).reshape(-1).view(np.uint8).data)
            k = 0
            while k < n:  # one write per run of frames inside one chunk
                f = at + k
                run = min(n - k, chunk - f % chunk)
                _pwrite(self._fd, buf[k * frame_bytes:(k + run) * frame_bytes],
                        int(offsets[f // chunk]) + (f % chunk) * frame_bytes)
                k += run

    def _crcs(self, at: int, arrays: Mapping[str, np.ndarray]) -> None:
        from pipeline.base.store import frame_checksum

        n = len(next(iter(arrays.values()))) if arrays else 0
        ordered = [arrays[name] for name in sorted(self._places)]
        for k in range(n):
            check = frame_checksum(ordered, k)
            with self._lock:
                self._stats.setdefault(str(at + k), {})["crc"] = check

    def commit(self, done_until: int, stats: Mapping[int, Mapping[str, Any]] | None = None) -> None:
        """Frames ``start : done_until`` are written: fsync them, then record it (with per-frame
        ``stats``, frame -> JSON-able dict, kept for :meth:`StreamedFile.finish`'s summary)."""
        with self._lock:
            for k, v in (stats or {}).items():
                self._stats.setdefault(str(int(k)), {}).update(v)
        os.fsync(self._fd)
        with self._lock:
            data = {"version": _PROGRESS_VERSION, "key": self.sf.provenance["iristac_key"], "start": self.start,
                    "stop": self.stop, "done": int(done_until), "stats": {k: dict(v) for k, v in self._stats.items()}}
        tmp = self.progress.with_name(self.progress.name + f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(data), encoding="utf-8")
        os.replace(tmp, self.progress)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> RangeWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _pwrite(fd: int, view: memoryview, offset: int) -> None:
    done = 0
    while done < len(view):
        done += os.pwrite(fd, view[done:], offset + done)
