"""H5Frames: HDF5 frames read straight into a caller's buffer (what the GPU pipeline's pinned
buffers receive; an ordinary array stands in for pinned memory here), by file offsets where the
data is unfiltered, through HDF5's filters where it is not; always the frames h5py reads."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from pipeline.base.h5frames import H5Frames

RNG = np.random.default_rng(5)
FRAMES = RNG.integers(0, 255, size=(7, 3, 10, 12, 3), dtype=np.uint8)


def _check(path, want_direct: bool, frames=FRAMES, threads: int = 3):
    with H5Frames(path, threads=threads) as src:
        assert src.direct is want_direct and src.shape == frames.shape and len(src) == len(frames)
        n = len(frames)
        for a, b in ((0, n), (2, 5), (n - 1, n), (3, 3)):
            dst = np.full((b - a,) + frames.shape[1:], 7, frames.dtype)
            src.read_into(dst, a, b)
            np.testing.assert_array_equal(dst, frames[a:b])


@pytest.mark.parametrize("layout,direct", [({}, True), ({"chunks": (1, 1, 10, 12, 3)}, True),
                                           ({"chunks": (3, 3, 10, 12, 3)}, True),  # a short last chunk
                                           ({"chunks": (1, 2, 10, 12, 3)}, True),
                                           ({"chunks": (1, 3, 5, 12, 3)}, False),  # chunks are not runs of frames
                                           ({"chunks": (1, 1, 10, 12, 3), "compression": "lzf"}, False)])
def test_layouts_read_what_h5py_reads(tmp_path, layout, direct):
    path = tmp_path / "f.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("frames", data=FRAMES, **layout)
    _check(path, direct)


def test_uint16_and_the_store_format(tmp_path):
    from pipeline.base.store import Record, write_record

    wide = FRAMES.astype(np.uint16) * 257
    with h5py.File(tmp_path / "w.h5", "w") as f:
        f.create_dataset("frames", data=wide)
    _check(tmp_path / "w.h5", True, wide)
    big = np.repeat(FRAMES, 30, axis=2)  # large enough that the store compresses it (the frames layout: zstd)
    P = big.shape[1]
    write_record(tmp_path / "capture.h5", Record("capture", {
        "frames": big, "reference": big[0], "drive": np.zeros((P, 24, 3), np.float32),
        "brightness": np.ones(P, np.float32)}, {"mm_per_px": 0.1, "pattern_names": ["a", "b", "c"], "source": "test"}))
    _check(tmp_path / "capture.h5", True, big)


def test_a_live_recording_while_and_after_recording(tmp_path):
    """While recording, FILE.h5 is virtual datasets over uncompressed segment files: read by
    offsets; once closed, one store-format file: its frames in Zstandard chunks, decoded on the threads."""
    from pipeline.live.recorder import LiveRecorder

    path = tmp_path / "rec.h5"
    rec = LiveRecorder(path, {"mode": "test", "solver": "nearfield"}, segment_results=2, segment_seconds=60.0)
    for k in range(len(FRAMES)):
        rec.add(frames=FRAMES[k], normals=np.zeros((10, 12, 3)), mask=np.ones((10, 12), bool),
                height=np.zeros((10, 12)), timestamp=float(k), latency_ms=1.0, index=k, dropped=0)
    _check(path, True, FRAMES[:6])  # three complete segments of two
    rec.close()
    _check(path, True)
    with H5Frames(path) as src:
        assert src.codec == "zstd"


def test_bad_destination_and_range_are_clear_errors(tmp_path):
    path = tmp_path / "f.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("frames", data=FRAMES)
    with H5Frames(path) as src:
        with pytest.raises(ValueError, match="writeable C-contiguous uint8 array"):
            src.read_into(np.zeros((2,) + FRAMES.shape[1:], np.uint16), 0, 2)
        with pytest.raises(ValueError, match="C-contiguous"):
            src.read_into(np.zeros((2, 12, 10, 3, 3), np.uint8).transpose(0, 3, 2, 1, 4)[:, :, :, :, :], 0, 2)
        with pytest.raises(IndexError, match="frames 5:9 of 7"):
            src.read_into(np.zeros((4,) + FRAMES.shape[1:], np.uint8), 5, 9)
    with pytest.raises(KeyError, match="no dataset 'images'"):
        H5Frames(path, "images")
