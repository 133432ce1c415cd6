"""The stage store: keys, atomic writes, crashes, concurrency, corruption."""

import multiprocessing as mp
import os
import signal
import subprocess
import sys
import textwrap
import time

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from helpers import REPO
from pipeline.base.frame_codec import layout_of
from pipeline.base.store import StageStore, StoreError, read_record, write_record
from schema_examples import example_record

# -- keys -------------------------------------------------------------------------------

def test_key_ignores_dict_order_and_int_vs_float_where_schema_says_number(tmp_path):
    s = StageStore(tmp_path)
    a = s.key("depth", 1, {"integrator": "dst", "mm_per_px": 1, "extra": {"b": 1, "a": [1, 2]}}, ["x"])
    b = s.key("depth", 1, {"extra": {"a": [1, 2], "b": 1}, "mm_per_px": 1.0, "integrator": "dst"}, ["x"])
    assert a.digest == b.digest


def test_int_vs_float_differs_where_schema_does_not_say_number(tmp_path):
    s = StageStore(tmp_path)
    # "frames_per_pattern" is an integer in the capture schema, "unknown" is undescribed.
    assert s.key("capture", 1, {"unknown": 1}).digest != s.key("capture", 1, {"unknown": 1.0}).digest


def test_arrays_hash_by_content_dtype_and_shape(tmp_path):
    s = StageStore(tmp_path)
    a = np.arange(6, dtype=np.float32)
    def k(v):
        return s.key("depth", 1, {"w": v}).digest

    assert k(a) == k(a.copy())
    assert k(a) != k(a + 1)
    assert k(a) != k(a.astype(np.float64))
    assert k(a) != k(a.reshape(2, 3))


@pytest.mark.parametrize("change", ["params", "inputs", "version", "stage", "input_order"])
def test_any_change_gives_a_new_key(tmp_path, change):
    s = StageStore(tmp_path)
    base = dict(stage="normals", version=1, params={"solver": "lstsq"}, inputs=["a", "b"])
    other = dict(base)
    if change == "params":
        other["params"] = {"solver": "robust"}
    elif change == "inputs":
        other["inputs"] = ["a", "c"]
    elif change == "version":
        other["version"] = 2
    elif change == "stage":
        other["stage"] = "depth"
    else:
        other["inputs"] = ["b", "a"]
    assert s.key(**base).digest != s.key(**other).digest


@settings(max_examples=50, deadline=None)
@given(st.dictionaries(st.text(min_size=1, max_size=5),
                       st.one_of(st.integers(-5, 5), st.floats(allow_nan=False, width=32), st.text(max_size=4)),
                       max_size=6))
def test_key_is_stable_under_reordering(params):
    s = StageStore("unused")
    reordered = dict(reversed(list(params.items())))
    assert s.key("depth", 1, params).digest == s.key("depth", 1, reordered).digest


def test_bad_stage_name_and_unknown_param_type(tmp_path):
    s = StageStore(tmp_path)
    with pytest.raises(ValueError, match="stage name"):
        s.key("../evil", 1, {})
    with pytest.raises(TypeError, match="stage parameter"):
        s.key("depth", 1, {"x": object()})


# -- put / get ----------------------------------------------------------------------------

def test_put_get_round_trip_records_provenance(tmp_path):
    s = StageStore(tmp_path)
    key = s.key("normals", 3, {"solver": "lstsq"}, ["cap", "cal"])
    assert s.get(key) is None
    rec = example_record("normals")
    path = s.put(key, rec)
    assert path == tmp_path / "normals" / f"{key.digest}.h5"
    back = s.get(key)
    np.testing.assert_array_equal(back.data["normals"], rec.data["normals"])
    p = back.provenance
    assert p["iristac_key"] == key.digest and p["iristac_stage"] == "normals"
    assert p["iristac_params"] == '{"solver":"lstsq"}' and p["iristac_inputs"] == '["cap", "cal"]'
    assert p["iristac_version"] and p["iristac_created"].endswith("+00:00")
    assert not list((tmp_path / "normals").glob(".*tmp*")), "no temporaries left after a clean write"


def test_get_or_compute_computes_once(tmp_path):
    s = StageStore(tmp_path)
    key = s.key("depth", 1, {"integrator": "fc"})
    calls = []

    def compute():
        calls.append(1)
        return example_record("depth")

    _, cached1 = s.get_or_compute(key, compute)
    _, cached2 = s.get_or_compute(key, compute)
    assert (cached1, cached2, len(calls)) == (False, True, 1)


def test_put_rejects_record_of_another_schema(tmp_path):
    s = StageStore(tmp_path)
    with pytest.raises(StoreError, match="stores schema 'depth'"):
        s.put(s.key("depth", 1, {}), example_record("normals"))


def test_image_stacks_are_compressed_and_chunked(tmp_path):
    rec = example_record("capture")
    rec.data["frames"] = np.zeros((2, 3, 64, 80, 3), np.uint8)
    rec.data["reference"] = np.zeros((3, 64, 80, 3), np.uint8)
    rec.data["dark"] = np.zeros((64, 80, 3), np.uint8)
    for k in [k for k in rec.data if k.startswith("truth/") or k in ("mask", "markers")]:  # image-sized extras
        del rec.data[k]
    path = write_record(tmp_path / "c.h5", rec)
    with h5py.File(path) as f:
        # frames: the frames layout (Zstandard chunks of one frame set, checksummed by zstd)
        assert layout_of(f["frames"]) == "zstd" and f["frames"].chunks == (1, 3, 64, 80, 3)
        # other image stacks: LZF, shuffle, Fletcher-32, one image a chunk
        assert f["reference"].compression == "lzf" and f["reference"].chunks == (1, 64, 80, 3)
        assert f["reference"].fletcher32
    np.testing.assert_array_equal(read_record(path).data["frames"], rec.data["frames"])


# -- crashes ----------------------------------------------------------------------------

_SLOW_WRITER = textwrap.dedent("""
    import sys, numpy as np
    sys.path.insert(0, {repo!r})
    from pipeline.base.store import Record, StageStore
    s = StageStore({root!r})
    key = s.key("capture", 1, {{"mode": "crash"}})
    # Big enough that the write takes a while: random data does not compress.
    frames = np.random.default_rng(0).integers(0, 255, (40, 24, 240, 320, 3), dtype=np.uint8)
    rec = Record("capture", {{"frames": frames, "reference": frames[0],
                              "drive": np.zeros((24, 6, 3), np.float32), "brightness": np.ones(24, np.float32)}},
                 {{"mm_per_px": 0.1, "pattern_names": ["p"] * 24, "source": "test"}})
    print("writing", flush=True)
    s.put(key, rec)
    print("done", flush=True)
""")


def test_sigkill_mid_write_leaves_no_valid_entry_and_gc_cleans(tmp_path):
    root = tmp_path / "store"
    code = _SLOW_WRITER.format(repo=str(REPO), root=str(root))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "writing"
    deadline = time.time() + 60
    temps = []
    while time.time() < deadline and not temps:
        assert proc.poll() is None, f"the writer died before writing: {proc.stderr.read()}"
        temps = [p for p in (root / "capture").glob(".*.tmp.h5")] if (root / "capture").is_dir() else []
        time.sleep(0.01)
    assert temps, "the writer never created its temporary file"
    time.sleep(0.2)  # let it get well into the data
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL

    s = StageStore(root)
    key = s.key("capture", 1, {"mode": "crash"})
    assert s.get(key) is None, "a killed writer must not leave an entry get() returns"
    assert [e.kind for e in s.entries()] == ["temp"]
    assert s.verify() == []
    removed = s.gc()
    assert removed == temps and not list((root / "capture").iterdir())


def test_gc_leaves_a_live_writers_temporary(tmp_path):
    d = tmp_path / "depth"
    d.mkdir()
    live = d / f".{'0' * 32}.{os.getpid()}.abc123.tmp.h5"
    live.write_bytes(b"partial")
    assert StageStore(tmp_path).gc() == [] and live.exists()


def _concurrent_writer(root, seed, barrier):
    from pipeline.base.store import StageStore
    from schema_examples import example_record

    s = StageStore(root)
    key = s.key("normals", 1, {"solver": "lstsq"})
    rec = example_record("normals", rng=np.random.default_rng(seed))
    rec.data["normals"] = np.random.default_rng(seed).standard_normal((2, 200, 300, 3)).astype(np.float32)
    rec.data["mask"] = np.ones((2, 200, 300), bool)
    for k in ("albedo", "residual", "condition", "confidence", "filled"):  # the other (H, W)-sized extras
        rec.data.pop(k, None)
    barrier.wait()
    for _ in range(3):
        s.put(key, rec)
    return seed


def test_two_processes_writing_the_same_key_leave_one_valid_entry(tmp_path):
    ctx = mp.get_context("spawn")
    barrier = ctx.Manager().Barrier(2)
    with ctx.Pool(2, initializer=_add_paths) as pool:
        results = pool.starmap(_concurrent_writer, [(str(tmp_path), 1, barrier), (str(tmp_path), 2, barrier)])
    assert sorted(results) == [1, 2]
    s = StageStore(tmp_path)
    entries = s.entries(check=True)
    assert [e.kind for e in entries] == ["entry"] and entries[0].problem is None
    rec = s.get(s.key("normals", 1, {"solver": "lstsq"}))
    winners = [np.random.default_rng(seed).standard_normal((2, 200, 300, 3)).astype(np.float32) for seed in (1, 2)]
    assert any(np.array_equal(rec.data["normals"], w) for w in winners)


def _add_paths():
    for p in (str(REPO), str(REPO / "tests")):
        if p not in sys.path:
            sys.path.insert(0, p)


# -- corruption ---------------------------------------------------------------------------

def _stored(tmp_path):
    s = StageStore(tmp_path)
    key = s.key("depth", 1, {"integrator": "dst"})
    rec = example_record("depth", all_datasets=False)  # height and mask, resized below
    rec.data["height"] = np.random.default_rng(0).standard_normal((2, 64, 64)).astype(np.float32)
    rec.data["mask"] = np.ones((2, 64, 64), bool)
    s.put(key, rec)
    return s, key, s.path_for(key)


def test_truncated_file_gives_one_clear_error(tmp_path):
    s, key, path = _stored(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(StoreError) as e:
        s.get(key)
    assert str(path) in str(e.value) and "truncated or corrupt" in str(e.value)
    assert "Traceback" not in str(e.value)


def test_flipped_data_bytes_are_caught_by_checksums(tmp_path):
    s, key, path = _stored(tmp_path)
    with h5py.File(path) as f:
        offset = f["height"].id.get_chunk_info(0).byte_offset
    raw = bytearray(path.read_bytes())
    for i in range(offset + 16, offset + 64):
        raw[i] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(StoreError, match=str(path)):
        s.get(key)
    bad = s.verify()
    assert len(bad) == 1 and bad[0].path == path


def test_schema_violating_file_gives_clear_error(tmp_path):
    s, key, path = _stored(tmp_path)
    with h5py.File(path, "a") as f:
        del f["mask"]
    with pytest.raises(StoreError, match=r"'mask' is a required property"):
        s.get(key)


def test_not_a_store_file(tmp_path):
    p = tmp_path / "foreign.h5"
    with h5py.File(p, "w") as f:
        f["x"] = np.zeros(3)
    with pytest.raises(StoreError, match="not an IrisTac store file"):
        read_record(p)
    with pytest.raises(StoreError, match="no such file"):
        read_record(tmp_path / "missing.h5")


def test_wrong_schema_and_newer_version(tmp_path):
    _, _, path = _stored(tmp_path)
    with pytest.raises(StoreError, match="expected a 'normals' file, found schema 'depth'"):
        read_record(path, schema="normals")
    with h5py.File(path, "a") as f:
        f.attrs["iristac_schema_version"] = 99
    with pytest.raises(StoreError, match="version 99"):
        read_record(path)


def test_bad_entry_is_a_miss_only_when_asked_and_is_kept(tmp_path):
    s, key, path = _stored(tmp_path)
    path.write_bytes(b"garbage" * 100)
    with pytest.raises(StoreError):
        s.get(key)
    assert s.get(key, recompute_bad=True) is None
    kept = list((tmp_path / "depth").glob("*.bad-*.h5"))
    assert len(kept) == 1 and kept[0].read_bytes() == b"garbage" * 100
    rec, cached = s.get_or_compute(key, lambda: example_record("depth"))
    assert not cached and s.get(key) is not None


def test_failed_write_keeps_previous_entry(tmp_path):
    s, key, path = _stored(tmp_path)
    before = path.read_bytes()
    bad = example_record("depth")
    bad.data["height"] = bad.data["height"].astype(np.int64)
    with pytest.raises(StoreError):
        s.put(key, bad)
    assert path.read_bytes() == before
    assert [e.kind for e in s.entries()] == ["entry"]


def test_clear_never_deletes_files_it_did_not_write(tmp_path):
    s, key, path = _stored(tmp_path)
    mine = tmp_path / "depth" / "notes.txt"
    mine.write_text("keep me")
    removed = s.clear()
    assert removed == [path] and mine.read_text() == "keep me"
