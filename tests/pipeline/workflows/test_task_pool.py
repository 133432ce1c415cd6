"""Batch processing: serial, process pool and a Dask LocalCluster agree; bad recordings are skipped."""

from functools import partial

import pytest

from batch_support import summarise_capture, write_capture
from pipeline.base.errors import UserError
from pipeline.base.store import StageStore
from pipeline.workflows.task_pool import format_summary, run_batch


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    d = tmp_path_factory.mktemp("recs")
    paths = []
    for i in range(8):
        p = d / f"rec{i:02d}.h5"
        write_capture(p, seed=i)
        paths.append(str(p))
    (d / "rec03.h5").write_bytes(b"this is not HDF5")  # one corrupt recording among them
    return paths


def _clean(items):
    return [(i.recording, i.ok, i.result, i.error) for i in items]


def test_pool_matches_serial_and_skips_the_corrupt_recording(recordings, tmp_path):
    task = partial(summarise_capture, store_root=str(tmp_path / "store"))
    serial = run_batch(recordings, task)
    pooled = run_batch(recordings, task, workers=2)
    assert _clean(serial) == _clean(pooled)
    bad = [i for i in serial if not i.ok]
    assert [i.recording for i in bad] == [recordings[3]]
    assert recordings[3] in bad[0].error and "not a readable HDF5 file" in bad[0].error
    assert sum(i.ok for i in serial) == 7
    store = StageStore(tmp_path / "store")
    assert len([e for e in store.entries(check=True) if e.kind == "entry" and not e.problem]) == 7
    table = format_summary(serial, ["mean_diff"])
    assert "FAILED" in table and "7 of 8 recordings processed, 1 failed" in table


def test_dask_local_cluster_matches_serial(recordings, tmp_path):
    distributed = pytest.importorskip("distributed")
    task = partial(summarise_capture, store_root=str(tmp_path / "store"))
    serial = run_batch(recordings, task)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40) as cluster:
        on_cluster = run_batch(recordings, task, scheduler=cluster.scheduler_address)
    assert _clean(on_cluster) == _clean(serial)


def test_unreachable_scheduler_and_bad_workers_are_clear_errors():
    with pytest.raises(UserError, match="cannot reach a Dask scheduler"):
        run_batch(["x"], len, scheduler="tcp://127.0.0.1:9", connect_timeout=1)
    with pytest.raises(UserError, match="--workers must be at least 1"):
        run_batch(["x"], len, workers=0)
