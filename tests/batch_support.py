"""A real batch task for the batch-engine tests: summarise a capture file through the store.

It lives in an importable module (not a test file) so that spawned workers and Dask workers
can unpickle it.
"""

import numpy as np

from pipeline.base.store import Record, StageStore, read_record


def summarise_capture(path: str, store_root: str) -> dict:
    rec = read_record(path, schema="capture")
    frames = rec.data["frames"].astype(np.float64)
    diff = frames - rec.data["reference"][None].astype(np.float64)
    store = StageStore(store_root)
    key = store.key("depth", 1, {"integrator": "fc", "task": "summary"}, [path])
    h = diff.mean(axis=(1, 4)).astype(np.float32)
    store.put(key, Record("depth", {"height": h, "mask": np.ones(h.shape, bool)},
                          {"integrator": "fc", "mm_per_px": float(rec.meta["mm_per_px"])}))
    return {"mean_diff": float(diff.mean()), "max_diff": float(np.abs(diff).max()), "key": key.digest}


def write_capture(path, seed: int) -> None:
    from pipeline.base.store import write_record

    rng = np.random.default_rng(seed)
    ref = rng.integers(0, 200, (2, 12, 16, 3), dtype=np.uint8)
    frames = np.clip(ref[None].astype(int) + rng.integers(0, 50, (2, 2, 12, 16, 3)), 0, 255).astype(np.uint8)
    write_record(path, Record("capture", {"frames": frames, "reference": ref,
                                          "drive": rng.random((2, 24, 3)).astype(np.float32),
                                          "brightness": np.ones(2, np.float32)},
                              {"mm_per_px": 0.1, "pattern_names": ["a", "b"], "source": "test"}))
