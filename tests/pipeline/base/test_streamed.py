"""Streamed store files: written by offset a range at a time, resumed, finished, checked (real HDF5 files)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from pipeline.base.errors import UserError
from pipeline.base.store import StageStore, StoreError, read_record
from pipeline.base.streamed import StreamedFile, merge_ranges, partial_path, progress_files

LAYOUT = {"height": ((6, 7), "float32"), "mask": ((6, 7), "bool")}
META = {"integrator": "dst", "mm_per_px": 0.1}


def _frames(a, b, seed=0):
    rng = np.random.default_rng(seed + a)
    return {"height": rng.normal(size=(b - a, 6, 7)).astype(np.float32), "mask": rng.random((b - a, 6, 7)) > 0.5}


def _open(path, frames=10, **kw):
    return StreamedFile.open(path, "depth", frames, LAYOUT, meta=META, **kw)


def test_ranges_written_out_of_order_read_back_exactly(tmp_path):
    final = tmp_path / "d.h5"
    sf = _open(final)
    for a, b in [(6, 10), (0, 3), (3, 6)]:  # as workers might finish them
        with sf.writer(a, b) as w:
            w.write(a, _frames(a, b))
            w.commit(b)
    assert sf.missing() == [] and not final.exists()
    sf.finish({"valid_fraction": 0.5})
    assert final.is_file() and not partial_path(final).exists() and progress_files(final) == []
    rec = read_record(final, "depth")
    want = {k: np.concatenate([_frames(a, b)[k] for a, b in [(0, 3), (3, 6), (6, 10)]]) for k in LAYOUT}
    np.testing.assert_array_equal(rec.data["height"], want["height"])
    np.testing.assert_array_equal(rec.data["mask"], want["mask"])
    assert rec.meta["valid_fraction"] == 0.5 and rec.meta["stream_digest"]
    with h5py.File(final) as f:  # chunked runs of whole frames, unfiltered
        assert f["height"].chunks[1:] == (6, 7) and f["height"].compression is None


def test_a_new_process_resumes_what_the_progress_files_claim_and_a_new_layout_starts_over(tmp_path):
    final = tmp_path / "d.h5"
    sf = _open(final)
    with sf.writer(0, 10) as w:
        w.write(0, _frames(0, 4))
        w.commit(4)
        w.write(4, _frames(4, 6))  # written, never committed: not claimed
    again = _open(final)
    assert again.missing() == [(4, 10)]
    assert _open(final, frames=12).missing() == [(0, 12)]  # another length: a fresh file
    assert progress_files(final) == []


def test_finish_refuses_missing_frames_and_renames_nothing(tmp_path):
    final = tmp_path / "d.h5"
    sf = _open(final)
    with sf.writer(0, 4) as w:
        w.write(0, _frames(0, 4))
        w.commit(4)
    with pytest.raises(UserError, match=r"frames 4:10 of 10 not written yet"):
        sf.finish()
    assert not final.exists() and partial_path(final).exists()


def test_a_flipped_bit_in_a_finished_file_is_found_by_the_store(tmp_path):
    store = StageStore(tmp_path / "store")
    key = store.key("depth", 1, {"integrator": "dst", "mm_per_px": 0.1}, inputs=["x"])
    sf = StreamedFile.open(store.path_for(key), "depth", 4, LAYOUT, meta=META, key=key)
    with sf.writer(0, 4) as w:
        w.write(0, _frames(0, 4))
        w.commit(4)
    path = sf.finish()
    assert store.get(key) is not None
    with h5py.File(path) as f:
        offset = f["height"].id.get_chunk_info(0).byte_offset + 9
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x10
    path.write_bytes(bytes(data))
    with pytest.raises(StoreError, match="stream_digest"):
        store.get(key)
    assert store.get(key, recompute_bad=True) is None  # quarantined, recomputed by the caller
    assert list(path.parent.glob("*.bad-*.h5"))


def test_progress_files_are_whole_json_and_name_their_key(tmp_path):
    final = tmp_path / "d.h5"
    sf = _open(final)
    with sf.writer(2, 5) as w:
        w.write(2, _frames(2, 5))
        w.commit(5, {2: {"valid": 3}})
    (p,) = progress_files(final)
    d = json.loads(p.read_text())
    assert (d["start"], d["done"], d["stats"]["2"]["valid"]) == (2, 5, 3) and "crc" in d["stats"]["4"]
    assert merge_ranges([(0, 2), (2, 5), (7, 8)]) == [(0, 5), (7, 8)]


def test_the_store_lists_a_partial_entry_keeps_it_on_gc_and_removes_it_on_clear(tmp_path):
    store = StageStore(tmp_path / "store")
    key = store.key("depth", 1, {"integrator": "dst", "mm_per_px": 0.1}, inputs=["y"])
    sf = StreamedFile.open(store.path_for(key), "depth", 4, LAYOUT, meta=META, key=key)
    with sf.writer(0, 2) as w:
        w.write(0, _frames(0, 2))
        w.commit(2)
    kinds = sorted(e.kind for e in store.entries())
    assert kinds == ["partial", "partial"]  # the partial file and its progress file
    assert store.gc(include_live=True) == [] and len(store.entries()) == 2  # resumable work is kept
    assert len(store.clear()) == 2 and store.entries() == []
