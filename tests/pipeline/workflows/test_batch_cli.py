"""``iristac batch``: 20 rendered recordings, one corrupt, serial == process pool == Dask LocalCluster."""

from __future__ import annotations

import json

import pytest

from helpers import run_cli
from pipeline.base.errors import UserError
from pipeline.base.store import StageStore, write_record
from pipeline.stages.synthesize import illumination_record
from pipeline.workflows.batch import SUMMARY_COLUMNS, batch_reconstruct
from pipeline.workflows.task_pool import format_summary
from sim.contacts import contact_surfaces

SHAPE, PX = (12, 16), 0.5
BAD = 7  # index of the corrupt recording


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    from pipeline.base.capture import write_capture
    from sim.render import bare_ring_illumination
    from sim.rendered_capture import render_capture

    d = tmp_path_factory.mktemp("batch")
    model = bare_ring_illumination(SHAPE, PX)
    ill = write_record(d / "illumination.h5", illumination_record(model))
    recs = d / "recs"
    paths = []
    for i in range(20):
        p = recs / f"rec{i:02d}.h5"
        surfaces = contact_surfaces("sphere", SHAPE, PX, 1, size_mm=1.5, depth_mm=0.2 + 0.02 * i, seed=i)
        write_capture(p, render_capture(model, "monochromatic", surfaces, seed=i))
        paths.append(str(p))
    # A truncated copy of a good file: a valid HDF5 signature, then nothing readable.
    (recs / f"rec{BAD:02d}.h5").write_bytes(open(paths[0], "rb").read()[:2048])
    return {"dir": d, "illumination": str(ill), "paths": paths}


@pytest.fixture(scope="module")
def serial(recordings, tmp_path_factory):
    store = tmp_path_factory.mktemp("serial-store")
    items = batch_reconstruct(recordings["paths"], illumination=recordings["illumination"], solver="nearfield",
                              store=str(store))
    return items, store


def outcome(items):
    return [(i.recording, i.ok, i.result, i.error) for i in items]


def test_serial_run_skips_the_corrupt_recording_and_reconstructs_the_rest(recordings, serial):
    items, store = serial
    assert [i.ok for i in items] == [i != BAD for i in range(20)]
    assert recordings["paths"][BAD] in items[BAD].error
    good = [i.result for i in items if i.ok]
    assert all(r["normal_mean_error_deg"] < 5 for r in good)  # lights exactly those rendered with
    assert len({r["depth_sha256"] for r in good}) == 19  # 19 different presses, 19 different results
    assert StageStore(store).verify() == []


def test_local_cluster_matches_serial_exactly_with_concurrent_writers(recordings, serial, tmp_path):
    distributed = pytest.importorskip("distributed")
    store = tmp_path / "store"
    # rec00 twice: two workers write the same store entry at the same time.
    paths = recordings["paths"] + [recordings["paths"][0]]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40) as cluster:
        items = batch_reconstruct(paths, illumination=recordings["illumination"], solver="nearfield",
                                  store=str(store), scheduler=cluster.scheduler_address)
    assert outcome(items[:20]) == outcome(serial[0])
    assert items[20].result == items[0].result
    # Really spread over both workers (a recording that fails to open fails in the planning process).
    assert len({w for i in items if i.ok for w in i.worker.split(",")}) == 2
    assert StageStore(store).verify() == []
    entries = [e for e in StageStore(store).entries() if e.kind == "entry"]
    assert len(entries) == 2 * 19  # normals + depth per good recording, the duplicate stored once


def test_cli_process_pool_matches_serial_and_prints_the_summary(recordings, serial, tmp_path):
    r = run_cli("batch", recordings["dir"] / "recs", "--illumination", recordings["illumination"],
                "--solver", "nearfield", "--workers", "2", "--cache", tmp_path / "store", "--json")
    assert r.returncode == 1, r.stderr  # some recordings failed; the rest were processed
    out = json.loads(r.stdout)
    assert (out["processed"], out["failed"]) == (19, 1)
    want = [i.to_json() for i in serial[0]]
    got = out["items"]
    assert [(g["recording"], g["ok"], g["result"], g["error"]) for g in got] == \
        [(w["recording"], w["ok"], w["result"], w["error"]) for w in want]
    table = format_summary(serial[0], SUMMARY_COLUMNS)  # what the CLI prints without --json
    assert "19 of 20 recordings processed, 1 failed" in table
    assert "FAILED" in table and "normal_mean_error_deg" in table


def test_cli_bad_inputs_are_one_clear_line(recordings, tmp_path):
    r = run_cli("batch", recordings["paths"][0], "--calibration", tmp_path / "nope.h5")
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0
    assert "--calibration" in r.stderr and "nope.h5: no such file" in r.stderr
    with pytest.raises(UserError, match="missing.h5: no such recording"):
        batch_reconstruct([tmp_path / "missing.h5"], illumination=recordings["illumination"])
    with pytest.raises(UserError, match="cannot reach a Dask scheduler"):
        batch_reconstruct(recordings["paths"][:1], illumination=recordings["illumination"],
                          scheduler="tcp://127.0.0.1:9", connect_timeout=1)
