"""How frame stacks are stored in HDF5: the ``frames`` of captures and finished live recordings.

One place for the choice (``docs/storage.md`` has the figures of ``iristac bench codec``
behind it) and for the one thing every HDF5 reader needs first:

- :func:`h5py_with_filters`: h5py after ``hdf5plugin`` has registered its filters (Zstd,
  Blosc2, LZ4 ...), so that HDF5 itself (``read_record``, h5py, ``h5dump`` with the plugin
  path) decodes files written with them. Every module of the project that opens HDF5 files
  imports h5py through it.
- :func:`write_frames`: a stack ``(K, ...)`` as chunks of one frame set each (runs of whole
  frames), each chunk one Zstandard frame at level :data:`ZSTD_LEVEL` (-1, a "fast" level)
  with its content size and an XXH64 checksum of the decoded bytes, compressed on several
  threads by ``zstandard`` and written with ``write_direct_chunk``; the dataset carries the
  Zstd filter of ``hdf5plugin`` (HDF5 filter id 32015), so any HDF5 reader with that plugin
  decodes it. The checksum, verified by our decoders below, replaces the store's Fletcher-32
  for these datasets.
- :func:`decode_chunk`: one stored chunk into a caller's buffer (``zstandard`` releases the
  GIL, so :class:`pipeline.base.h5frames.H5Frames` decodes on several threads);
  :func:`read_frames`: a whole dataset so (what ``read_record`` reads these datasets with).
  Both verify every chunk's checksum. HDF5's own Zstd filter (``hdf5plugin``) decodes the same
  chunks but ignores a checksum mismatch (measured: a flipped bit comes back as a changed
  byte, no error), so the project never reads these datasets through it.

Examples
--------
>>> import tempfile, os, numpy as np
>>> h5py = h5py_with_filters()
>>> path = os.path.join(tempfile.mkdtemp(), "f.h5")
>>> frames = np.arange(5 * 2 * 8 * 3, dtype=np.uint8).reshape(5, 2, 8, 3)
>>> with h5py.File(path, "w") as f:
...     _ = write_frames(f, "frames", frames)
...     ds = f["frames"]
...     ds.chunks, layout_of(ds), bool((ds[1:3] == frames[1:3]).all())
((1, 2, 8, 3), 'zstd', True)
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

__all__ = ["FRAMES_CODEC", "ZSTD_FILTER", "ZSTD_LEVEL", "decode_chunk", "h5py_with_filters", "layout_of",
           "read_frames", "write_frames"]

#: The layout :func:`write_frames` writes (the name :func:`layout_of` gives it).
FRAMES_CODEC = "zstd"
#: HDF5's registered filter id of Zstandard (what ``hdf5plugin.Zstd`` writes).
ZSTD_FILTER = 32015
#: Zstandard level of :func:`write_frames`. ``iristac bench codec`` (docs/storage.md): level -1
#: (literals left without entropy coding) decodes 1.4-2.2x faster than level 1 for 6-12 % more
#: size, and is about the size of the LZF it replaces; level -3 is faster still but larger
#: than LZF on the real frames.
ZSTD_LEVEL = -1
#: Threads that compress chunks in :func:`write_frames`.
WRITE_THREADS = 4


def h5py_with_filters():
    """The h5py module, after ``hdf5plugin`` registered its filters with HDF5 (once a process)."""
    import h5py
    import hdf5plugin  # noqa: F401  (registers Zstd, Blosc2, LZ4 ... with the HDF5 library)

    return h5py


def layout_of(ds) -> str:
    """How a dataset's bytes are stored: ``raw`` (no filter), ``zstd`` (only the Zstd filter),
    ``lzf`` (LZF with or without shuffle and Fletcher-32, the stage store's), else the
    filters' names joined by ``+`` (HDF5 decodes them, on one thread)."""
    plist = ds.id.get_create_plist()
    names = []
    for i in range(plist.get_nfilters()):
        code = plist.get_filter(i)[0]
        names.append({1: "deflate", 2: "shuffle", 3: "fletcher32", 32000: "lzf", ZSTD_FILTER: "zstd",
                      32001: "blosc", 32026: "blosc2", 32004: "lz4", 32008: "bitshuffle"}.get(code, str(code)))
    if not names:
        return "raw"
    if names == ["zstd"]:
        return "zstd"
    if "lzf" in names and set(names) <= {"lzf", "shuffle", "fletcher32"}:
        return "lzf"
    return "+".join(names)


def write_frames(f, name: str, frames, *, level: int = ZSTD_LEVEL, threads: int = WRITE_THREADS):
    """Create dataset ``name`` of ``f`` holding ``frames`` ``(K, ...)`` in the frames layout
    (one Zstandard frame per frame set, checksummed); returns the dataset."""
    import zstandard

    h5py_with_filters()
    arr = np.ascontiguousarray(frames)
    if arr.ndim < 2 or arr.shape[0] == 0 or arr.size == 0:
        return f.create_dataset(name, data=arr)
    ds = f.create_dataset(name, shape=arr.shape, dtype=arr.dtype, chunks=(1,) + arr.shape[1:],
                          compression=ZSTD_FILTER,
                          # the level as the filter's unsigned parameter (hdf5plugin.Zstd's way for negative levels)
                          compression_opts=(int(level) & 0xFFFFFFFF,))
    zero = (0,) * (arr.ndim - 1)

    def pack(k: int) -> bytes:
        # a compressor per call: zstandard's are not thread-safe; creating one costs microseconds
        c = zstandard.ZstdCompressor(level=int(level), write_checksum=True, write_content_size=True)
        return c.compress(arr[k].data)

    n = max(1, min(int(threads), len(arr)))
    if n == 1:
        for k in range(len(arr)):
            ds.id.write_direct_chunk((k,) + zero, pack(k))
        return ds
    with ThreadPoolExecutor(n, thread_name_prefix="iristac-zstd") as pool:
        # in order, a window at a time: compression runs ahead of the (serialised) HDF5 writes
        window = 4 * n
        pending: dict[int, Any] = {}
        for k in range(len(arr)):
            pending[k] = pool.submit(pack, k)
            if k >= window:
                ds.id.write_direct_chunk((k - window,) + zero, pending.pop(k - window).result())
        for k in sorted(pending):
            ds.id.write_direct_chunk((k,) + zero, pending.pop(k).result())
    return ds


_LOCAL = threading.local()  # a decompressor per thread: zstandard's must not be shared by threads at once


def decode_chunk(codec: str, data, dst: memoryview) -> None:
    """Decode one stored chunk of layout ``codec`` (``zstd``, or ``raw`` for a chunk stored
    unfiltered) into ``dst`` (exactly its decoded size). Raises ``ValueError`` saying what is
    wrong (a checksum mismatch, a truncated frame, the wrong size)."""
    if codec == "raw":
        if len(data) != len(dst):
            raise ValueError(f"{len(data)} bytes stored, {len(dst)} expected")
        dst[:] = data
        return
    import zstandard

    dctx = getattr(_LOCAL, "dctx", None)
    if dctx is None:
        dctx = _LOCAL.dctx = zstandard.ZstdDecompressor()
    try:
        # straight into the caller's memory (no copy); zstd checks the frame's checksum at its end
        with dctx.stream_reader(data, read_across_frames=False) as reader:
            n = reader.readinto(dst)
            more = reader.read(1)
    except zstandard.ZstdError as exc:
        raise ValueError(f"zstd: {exc}") from None
    if n != len(dst) or more:
        raise ValueError(f"{n}{'+' if more else ''} bytes decoded, {len(dst)} expected")


def read_frames(ds, *, threads: int = WRITE_THREADS) -> np.ndarray:
    """All of dataset ``ds`` (layout ``zstd``, chunks of whole frames), each chunk's checksum
    verified: raw chunks read by h5py (``read_direct_chunk``), decoded on ``threads`` threads.
    A dataset in another layout, or with chunks missing, is read by h5py as usual. Raises
    ``ValueError`` naming the frames of a chunk that does not decode."""
    shape, chunks = tuple(ds.shape), ds.chunks
    if layout_of(ds) != "zstd" or chunks is None or len(shape) == 0 or tuple(chunks[1:]) != shape[1:] \
            or ds.id.get_num_chunks() != -(-shape[0] // chunks[0]):
        return ds[()]
    out = np.empty(shape, ds.dtype)
    frame = out[0].nbytes if len(out) else 0
    buf = out.reshape(-1).view(np.uint8).data
    per, zero = int(chunks[0]), (0,) * (len(shape) - 1)

    def job(k: int, mask: int, data) -> None:
        a, b = k * frame, min(len(out), k + per) * frame
        try:
            decode_chunk("raw" if mask & 1 else "zstd", data, buf[a:b])
        except ValueError as exc:
            raise ValueError(f"frames {k}:{min(len(out), k + per)} of {ds.name.lstrip('/')!r}: {exc}") from None

    with ThreadPoolExecutor(max(1, int(threads)), thread_name_prefix="iristac-zstd") as pool:
        futures = [pool.submit(job, k, *ds.id.read_direct_chunk((k,) + zero)) for k in range(0, len(out), per)]
        for f in futures:
            f.result()
    return out
