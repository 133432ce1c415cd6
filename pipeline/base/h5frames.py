"""Frames of an HDF5 file read straight into a caller's buffer (a GPU pipeline's pinned memory).

:class:`H5Frames` reads frames ``start:stop`` of a dataset (``frames (K, P, H, W, C)`` of a
capture, a live recording) into a C-contiguous array the caller owns, with no copy between:

- **unfiltered data** (contiguous, chunked with chunks that are runs of whole frames, or a
  virtual dataset over such sources, as ``iristac live --record`` writes): the bytes' places
  in the files are read once from HDF5 (public h5py calls: ``DatasetID.get_offset``,
  ``chunk_iter``/``get_chunk_info``, ``Dataset.virtual_sources``), then the frames are read with
  ``os.preadv`` on several threads at once, into the buffer (the reads release the GIL, so
  page-cache copies run on several cores);
- **Zstandard chunks of whole frames** (what captures and finished recordings hold,
  :mod:`pipeline.base.frame_codec`): the chunks' places and sizes are read once
  (``chunk_iter``), then each chunk is read with ``os.pread`` and decoded by ``zstandard``
  straight into the buffer, chunks on several threads at once (both release the GIL; zstd
  verifies each chunk's checksum);
- **other filtered data** (the stage store's LZF, shuffle and Fletcher-32, as captures were
  written before; any other filter): ``Dataset.read_direct`` into the buffer, through HDF5's
  filter pipeline on one thread (h5py serialises HDF5 calls). Decompression bounds it
  (measured 0.09-0.18 GB/s for LZF: 50-100 frame sets of 8 x 320 x 240 x 3 a second on one core).

A file that cannot be read (truncated, a corrupt chunk) raises
:class:`pipeline.base.store.StoreError` naming the file and the frames.

Examples
--------
>>> import tempfile, os, h5py
>>> path = os.path.join(tempfile.mkdtemp(), "f.h5")
>>> with h5py.File(path, "w") as f:
...     _ = f.create_dataset("frames", data=np.arange(4 * 2 * 3, dtype=np.uint8).reshape(4, 2, 3))
>>> with H5Frames(path) as src:
...     dst = np.zeros((2, 2, 3), np.uint8)
...     src.read_into(dst, 1, 3)
...     src.direct, dst[0].tolist()
(True, [[6, 7, 8], [9, 10, 11]])
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.frame_codec import decode_chunk, h5py_with_filters, layout_of
from pipeline.base.store import StoreError

__all__ = ["H5Frames"]

#: Bytes per read call on the direct path (a few per thread and batch).
PIECE = 8 << 20


class H5Frames:
    """Frames ``start:stop`` of dataset ``name`` of an HDF5 file, read into a caller's array.

    Parameters
    ----------
    path : path
    name : str
        The dataset (first axis: frames).
    threads : int
        Reader threads of the direct path.

    Attributes
    ----------
    shape, dtype : the dataset's
    direct : bool
        True when the frames are read by file offsets on the reader threads (unfiltered data,
        Zstandard chunks decoded on those threads), False when through HDF5's filter pipeline.
    codec : str
        How the dataset is stored (:func:`pipeline.base.frame_codec.layout_of`: ``raw``,
        ``zstd``, ``lzf``, ...; ``virtual`` for a virtual dataset).
    """

    def __init__(self, path, name: str = "frames", threads: int = 8):
        h5py = h5py_with_filters()

        self.path = Path(path)
        try:
            # no chunk cache: frames are read once, in order (a cache only copies them once more)
            self._file = h5py.File(self.path, "r", rdcc_nbytes=0)
        except FileNotFoundError:
            raise StoreError(self.path, "no such file") from None
        except OSError as exc:
            raise StoreError(self.path, f"not a readable HDF5 file (truncated or corrupt?): {exc}") from None
        if name not in self._file:
            self._file.close()
            raise KeyError(f"{self.path}: no dataset {name!r}")
        self._ds = self._file[name]
        self.shape = tuple(self._ds.shape)
        self.dtype = np.dtype(self._ds.dtype)
        self.frame_bytes = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        self._fds: dict[str, int] = {}
        try:
            self.codec = "virtual" if self._ds.is_virtual else layout_of(self._ds)
            extents = _extents(self._ds, self.path)
            total = self.frame_bytes * (self.shape[0] if self.shape else 0)
            if extents is not None and sum(e[1] for e in extents) != total:
                extents = None  # a part not written yet (fill values): HDF5 knows what to return
            self._chunks = _zstd_chunks(self._ds, self.frame_bytes) if extents is None and self.codec == "zstd" else None
        except Exception as exc:
            self._file.close()
            raise StoreError(self.path, f"dataset {name!r}: cannot read its layout (truncated or corrupt?): {exc}") \
                from None
        self._extents = extents
        self.direct = extents is not None or self._chunks is not None
        if self._chunks is not None:
            self._fd(str(self.path))  # opened here, not by the reader threads at once
        self.threads = max(1, int(threads))
        self._pool: ThreadPoolExecutor | None = None

    def __len__(self) -> int:
        return int(self.shape[0])

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        for fd in self._fds.values():
            os.close(fd)
        self._fds.clear()
        self._file.close()

    def __enter__(self) -> H5Frames:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def read_into(self, dst: np.ndarray, start: int, stop: int) -> None:
        """Frames ``start:stop`` into ``dst`` (C-contiguous, writeable, ``(stop - start,) + shape[1:]``
        of the dataset's dtype: e.g. the numpy view of a pinned torch tensor)."""
        want = (stop - start,) + self.shape[1:]
        if not (0 <= start <= stop <= len(self)):
            raise IndexError(f"H5Frames {self.path}: frames {start}:{stop} of {len(self)}")
        if dst.shape != want or dst.dtype != self.dtype or not dst.flags.c_contiguous or not dst.flags.writeable:
            raise ValueError(f"H5Frames {self.path}: dst must be a writeable C-contiguous {self.dtype} array {want}, "
                             f"got {dst.dtype} {dst.shape}")
        if stop == start:
            return
        try:
            self._read(dst, start, stop)
        except StoreError:
            raise
        except Exception as exc:  # h5py's OSError/RuntimeError, a short read, a corrupt zstd chunk
            raise StoreError(self.path, f"frames {start}:{stop} of {self._ds.name.lstrip('/')!r}: cannot be read "
                                        f"(truncated or corrupt?): {exc}") from None

    def _read(self, dst: np.ndarray, start: int, stop: int) -> None:
        buf = dst.reshape(-1).view(np.uint8).data  # a memoryview of the caller's memory
        if self._chunks is not None:
            jobs: list[tuple[Any, ...]] = [(buf, *c) for c in self._chunk_jobs(start, stop)]
            work: Any = self._decode
        elif self._extents is not None:
            jobs = [(buf, *p) for p in self._pieces(start * self.frame_bytes, stop * self.frame_bytes)]
            work = _pread
        else:
            self._ds.read_direct(dst, np.s_[start:stop], np.s_[0:stop - start])
            return
        if self.threads == 1 or len(jobs) == 1:
            for j in jobs:
                work(*j)
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="iristac-h5read")
        for f in [self._pool.submit(work, *j) for j in jobs]:
            f.result()

    def _fd(self, file: str) -> int:
        fd = self._fds.get(file)
        if fd is None:
            fd = self._fds[file] = os.open(file, os.O_RDONLY)
        return fd

    def _chunk_jobs(self, start: int, stop: int) -> list[tuple[int, int, int, int]]:
        """``(chunk, its first frame wanted, frames wanted, byte in the destination)`` of the
        chunks holding frames ``start:stop``."""
        assert self._chunks is not None
        per = self._chunks.frames
        out = []
        for c in range(start // per, (stop - 1) // per + 1):
            lo, hi = max(start, c * per), min(stop, (c + 1) * per)
            out.append((c, lo - c * per, hi - lo, (lo - start) * self.frame_bytes))
        return out

    def _decode(self, buf: memoryview, c: int, first: int, n: int, at: int) -> None:
        assert self._chunks is not None
        offset, size, raw = self._chunks.table[c]
        data = os.pread(self._fd(str(self.path)), size, offset)  # releases the GIL
        if len(data) != size:
            raise StoreError(self.path, f"chunk at byte {offset}: {len(data)} of {size} bytes in the file (truncated?)")
        whole = min(self._chunks.frames, len(self) - c * self._chunks.frames) * self.frame_bytes
        codec = "raw" if raw else "zstd"
        try:
            if first == 0 and n * self.frame_bytes == whole:
                decode_chunk(codec, data, buf[at:at + whole])
            else:  # a chunk in part: decoded aside, its frames copied
                tmp = bytearray(self._chunks.frames * self.frame_bytes)
                decode_chunk(codec, data, memoryview(tmp)[:whole])
                buf[at:at + n * self.frame_bytes] = memoryview(tmp)[first * self.frame_bytes:(first + n) * self.frame_bytes]
        except ValueError as exc:
            raise StoreError(self.path, f"frames {c * self._chunks.frames}:{c * self._chunks.frames + whole // self.frame_bytes} "
                                        f"of {self._ds.name.lstrip('/')!r} (chunk at byte {offset}, {size} bytes): "
                                        f"corrupt: {exc}") from None

    def _pieces(self, a: int, b: int) -> list[tuple[int, int, int, int]]:
        """``(fd, file offset, offset in the destination, bytes)`` covering dataset bytes ``a:b``."""
        assert self._extents is not None
        out = []
        for start, n, file, offset in self._extents:
            lo, hi = max(a, start), min(b, start + n)
            if lo >= hi:
                continue
            fd = self._fd(file)
            for p in range(lo, hi, PIECE):
                q = min(hi, p + PIECE)
                out.append((fd, offset + (p - start), p - a, q - p))
        return out


def _pread(buf: memoryview, fd: int, offset: int, at: int, n: int) -> None:
    view = buf[at:at + n]
    done = 0
    while done < n:
        got = os.preadv(fd, [view[done:]], offset + done)
        if got <= 0:
            raise OSError(f"short read: {done} of {n} bytes at offset {offset}")
        done += got


def _extents(ds, path: Path) -> list[tuple[int, int, str, int]] | None:
    """``(byte in the dataset, bytes, file, byte in the file)`` of every stored run of the
    dataset's C-order bytes, sorted; None when they cannot be read by offset (filtered data,
    chunks that are not runs of frames, a non-native or non-numeric dtype, a selection
    HDF5 would have to assemble)."""
    dt = np.dtype(ds.dtype)
    if dt.kind not in "biuf" or not dt.isnative or ds.shape is None or len(ds.shape) == 0:
        return None
    if ds.is_virtual:
        return _virtual_extents(ds, path)
    if ds.id.get_create_plist().get_nfilters() > 0 or ds.external:
        return None
    shape, item = tuple(ds.shape), dt.itemsize
    if ds.chunks is None:
        offset = ds.id.get_offset()
        return None if offset is None else [(0, int(np.prod(shape, dtype=np.int64)) * item, str(path), int(offset))]
    return _chunk_extents(ds, shape, tuple(ds.chunks), item, str(path))


def _chunk_extents(ds, shape, chunks, item: int, file: str):
    """Chunks that are runs of the C order (ones, then one axis ``a`` cut, then whole axes)."""
    a = next((i for i, c in enumerate(chunks) if c != 1), len(chunks) - 1)
    if any(c != s for c, s in zip(chunks[a + 1:], shape[a + 1:])):
        return None
    strides = np.cumprod((shape[1:] + (1,))[::-1])[::-1] * item  # bytes per step of each axis
    whole = int(np.prod(chunks[a:], dtype=np.int64)) * item
    infos: list[Any] = []
    if hasattr(ds.id, "chunk_iter"):
        ds.id.chunk_iter(infos.append)
    else:  # pragma: no cover - older h5py
        infos = [ds.id.get_chunk_info(i) for i in range(ds.id.get_num_chunks())]
    out = []
    for info in infos:
        at = int(sum(int(o) * int(s) for o, s in zip(info.chunk_offset, strides)))
        inside = min(chunks[a], shape[a] - info.chunk_offset[a])  # the last chunk along a: its prefix
        n = whole // chunks[a] * inside
        out.append((at, n, file, int(info.byte_offset)))
    return sorted(out)


def _virtual_extents(ds, path: Path):
    """A virtual dataset whose sources are blocks of whole frames of readable datasets."""
    import h5py

    shape = tuple(ds.shape)
    frame = int(np.prod(shape[1:], dtype=np.int64)) * np.dtype(ds.dtype).itemsize
    out = []
    for vmap in ds.virtual_sources():
        lo, hi = vmap.vspace.get_select_bounds()
        if any(lo[1:]) or tuple(h + 1 for h in hi[1:]) != shape[1:] or \
                vmap.vspace.get_select_npoints() != (hi[0] - lo[0] + 1) * int(np.prod(shape[1:], dtype=np.int64)):
            return None
        src_path = path if vmap.file_name == "." else Path(vmap.file_name)
        if not src_path.is_absolute():
            src_path = path.parent / src_path
        with h5py.File(src_path, "r") as f:
            src = f[vmap.dset_name]
            whole = (vmap.src_space.get_select_type() == h5py.h5s.SEL_ALL
                     or vmap.src_space.get_select_npoints() == src.size)
            if not whole or src.shape != (hi[0] - lo[0] + 1,) + shape[1:] or src.dtype != ds.dtype:
                return None
            parts = _extents(src, src_path)
        if parts is None:
            return None
        out += [(lo[0] * frame + at, n, file, offset) for at, n, file, offset in parts]
    return sorted(out)


class _Chunks:
    """Where each chunk of a Zstandard dataset is: ``table[c] = (byte in the file, bytes,
    stored unfiltered)``; ``frames`` per chunk."""

    def __init__(self, frames: int, table: list[tuple[int, int, bool]]):
        self.frames = frames
        self.table = table


def _zstd_chunks(ds, frame_bytes: int) -> _Chunks | None:
    """The chunk table of a dataset in Zstandard chunks of whole frames; None when its chunks
    are not runs of whole frames, when a chunk is missing (fill values) or the file is external."""
    shape, chunks = tuple(ds.shape), ds.chunks
    if chunks is None or ds.external or len(shape) == 0 or tuple(chunks[1:]) != shape[1:] or frame_bytes == 0:
        return None
    dt = np.dtype(ds.dtype)
    if dt.kind not in "biuf" or not dt.isnative:
        return None
    per = int(chunks[0])
    count = -(-shape[0] // per)
    table: list[Any] = [None] * count
    infos: list[Any] = []
    ds.id.chunk_iter(infos.append)
    for info in infos:
        c = int(info.chunk_offset[0]) // per
        table[c] = (int(info.byte_offset), int(info.size), bool(info.filter_mask & 1))
    if any(t is None for t in table):
        return None
    return _Chunks(per, table)
