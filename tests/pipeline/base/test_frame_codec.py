"""The frames layout of captures and recordings (Zstandard chunks of one frame set, each with
its checksum): bit-exact through ``read_record`` (HDF5's Zstd filter from hdf5plugin) and
``H5Frames`` (decoded on its threads); captures written before it (LZF) still read; a damaged
file is one clear error naming it."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.base import store
from pipeline.base.capture import Capture, read_capture, write_capture
from pipeline.base.frame_codec import h5py_with_filters, layout_of, write_frames
from pipeline.base.h5frames import H5Frames
from pipeline.base.store import StoreError, read_record

h5py = h5py_with_filters()
RNG = np.random.default_rng(7)
# Smooth images with noise (they compress, as camera frames do), 9 frame sets of 2 patterns.
_BASE = (np.add.outer(np.arange(40), np.arange(48)) % 200).astype(np.uint8)[None, None, :, :, None]
FRAMES = np.clip(_BASE + RNG.integers(0, 6, size=(9, 2, 40, 48, 3)), 0, 255).astype(np.uint8)


def _capture(frames=FRAMES) -> Capture:
    P = frames.shape[1]
    return Capture(frames=frames, reference=frames[0], drive=np.zeros((P, 24, 3), np.float32),
                   brightness=np.ones(P, np.float32), mm_per_px=0.1,
                   meta={"pattern_names": [f"p{i}" for i in range(P)], "source": "test"})


def _reads_back(path, frames, codec, direct):
    np.testing.assert_array_equal(read_record(path, "capture").data["frames"], frames)
    np.testing.assert_array_equal(read_capture(path).frames, frames)
    for threads in (1, 3):
        with H5Frames(path, "frames", threads=threads) as src:
            assert (src.codec, src.direct, src.shape, src.dtype, len(src)) == (codec, direct, frames.shape,
                                                                              frames.dtype, len(frames))
            n = len(frames)
            for a, b in ((0, n), (1, n - 2), (n - 1, n), (3, 3)):
                dst = np.full((b - a,) + frames.shape[1:], 3, frames.dtype)
                src.read_into(dst, a, b)
                np.testing.assert_array_equal(dst, frames[a:b])


def test_a_capture_is_written_in_zstd_chunks_of_one_frame_set_and_reads_bit_exactly(tmp_path):
    path = write_capture(tmp_path / "c.h5", _capture())
    with h5py.File(path) as f:
        ds = f["frames"]
        assert layout_of(ds) == "zstd" and ds.chunks == (1,) + FRAMES.shape[1:]
        assert ds.id.get_storage_size() < FRAMES.nbytes  # compressed
        assert layout_of(f["reference"]) == "lzf"  # the other large datasets: as the store writes them
    _reads_back(path, FRAMES, "zstd", True)


def test_uint16_frames_and_incompressible_frames(tmp_path):
    wide = FRAMES.astype(np.uint16) * 257
    _reads_back(write_capture(tmp_path / "w.h5", _capture(wide)), wide, "zstd", True)
    noise = RNG.integers(0, 256, size=(5, 1, 30, 20, 3), dtype=np.uint8)
    _reads_back(write_capture(tmp_path / "n.h5", _capture(noise)), noise, "zstd", True)


def test_a_capture_written_before_the_frames_layout_still_reads(tmp_path, monkeypatch):
    monkeypatch.setattr(store, "FRAME_SCHEMAS", ())  # the writer as it was: LZF, shuffle, Fletcher-32
    path = write_capture(tmp_path / "old.h5", _capture())
    monkeypatch.undo()
    with h5py.File(path) as f:
        assert f["frames"].compression == "lzf" and f["frames"].fletcher32 and f["frames"].shuffle
    _reads_back(path, FRAMES, "lzf", False)


def test_chunks_written_by_hdf5_through_the_plugin_also_read_on_threads(tmp_path):
    """hdf5plugin.Zstd writes the same chunks (no checksum): H5Frames decodes those too."""
    import hdf5plugin

    path = tmp_path / "p.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("frames", data=FRAMES, chunks=(3,) + FRAMES.shape[1:], **hdf5plugin.Zstd(clevel=2))
    with H5Frames(path, threads=2) as src:
        assert src.codec == "zstd" and src.direct
        dst = np.empty((5,) + FRAMES.shape[1:], np.uint8)
        src.read_into(dst, 2, 7)  # chunks of 3 frame sets: two read in part
        np.testing.assert_array_equal(dst, FRAMES[2:7])


def _chunk_place(path, k):
    with h5py.File(path) as f:
        info = f["frames"].id.get_chunk_info_by_coord((k, 0, 0, 0, 0))
        return int(info.byte_offset), int(info.size)


def test_a_corrupt_chunk_is_one_clear_error_naming_the_file(tmp_path):
    path = write_capture(tmp_path / "c.h5", _capture())
    offset, size = _chunk_place(path, 4)
    with open(path, "r+b") as fh:  # one bit of frame set 4's compressed bytes
        fh.seek(offset + size // 2)
        b = fh.read(1)
        fh.seek(offset + size // 2)
        fh.write(bytes([b[0] ^ 0x04]))
    with pytest.raises(StoreError, match=f"{path}: cannot read dataset data"):
        read_record(path)
    with H5Frames(path, threads=2) as src:
        dst = np.empty_like(FRAMES)
        src.read_into(dst[:4], 0, 4)  # the frames before it are fine
        np.testing.assert_array_equal(dst[:4], FRAMES[:4])
        with pytest.raises(StoreError, match=rf"{path}: frames 4:5 of 'frames' \(chunk at byte {offset}, "
                                             rf"{size} bytes\): corrupt: zstd"):
            src.read_into(dst, 0, len(FRAMES))


def test_a_truncated_file_is_one_clear_error_naming_the_file(tmp_path):
    path = write_capture(tmp_path / "c.h5", _capture())
    offset, _ = _chunk_place(path, 6)
    whole = path.read_bytes()
    path.write_bytes(whole[:offset + 10])  # cut inside frame set 6
    with pytest.raises(StoreError, match=str(path)):
        read_record(path)
    try:
        src = H5Frames(path, threads=2)
    except StoreError as exc:  # the file's own structure was cut off
        assert str(path) in str(exc)
        return
    with src, pytest.raises(StoreError, match=str(path)):
        src.read_into(np.empty_like(FRAMES), 0, len(FRAMES))


def test_write_frames_with_one_thread_and_an_empty_stack(tmp_path):
    with h5py.File(tmp_path / "f.h5", "w") as f:
        ds = write_frames(f, "frames", FRAMES, threads=1, level=3)
        np.testing.assert_array_equal(ds[()], FRAMES)
        empty = write_frames(f, "empty", np.zeros((0, 2, 4, 4, 3), np.uint8))
        assert empty.shape == (0, 2, 4, 4, 3)
