"""Long recordings through ``iristac batch``: killed with SIGKILL halfway and resumed, split into frame
ranges over worker processes, written at half precision, the contact mask added later (real files,
real processes)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from helpers import REPO, run_cli
from pipeline.base.store import read_record, write_record
from pipeline.base.streamed import partial_path, progress_files

SHAPE, PX, FRAMES = (24, 32), 0.25, 64

_KILLED = """
import glob, json, os, signal, sys, time
import pipeline.streaming.writer as stream_writer
from pipeline.streaming.frame_setup import prepare
from pipeline.streaming.frames import run_frames
from pipeline.streaming.plan import plan_stream
stream_writer.COMMIT_SECONDS = 0.0   # every chunk recorded as done once fsynced
job, cap, lights = plan_stream(sys.argv[1], illumination=sys.argv[2], solver="nearfield", store=sys.argv[3])
job.chunk = 8
seen = [0]

def claimed():
    done = {}
    for p in glob.glob(os.path.join(sys.argv[3], "*", ".*.progress-*.json")):
        try:
            done[os.path.dirname(p)] = max(done.get(os.path.dirname(p), 0), json.load(open(p))["done"])
        except (OSError, ValueError):
            pass
    return min(done.values()) if len(done) == 2 else 0

def progress(n):
    seen[0] += n
    if seen[0] >= 32:
        # Wait until both entries (normals, depth) record some frames, then kill: the writer and
        # the committing thread may be anywhere in the next chunk; SIGKILL cannot be caught.
        t = time.monotonic()
        while claimed() < 16 and time.monotonic() - t < 60:
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGKILL)
run_frames(job, threads=1, progress=progress, cap=cap, pipe=prepare(job, cap, lights, 1))
"""


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from pipeline.base.capture import write_capture
    from pipeline.stages.synthesize import illumination_record
    from sim.contacts import contact_surfaces
    from sim.render import bare_ring_illumination
    from sim.rendered_capture import render_capture

    d = tmp_path_factory.mktemp("long")
    model = bare_ring_illumination(SHAPE, PX)
    ill = write_record(d / "illumination.h5", illumination_record(model))
    surfaces = contact_surfaces("sphere", SHAPE, PX, FRAMES, size_mm=2.0, depth_mm=0.4, spread_mm=1.5, seed=3)
    rec = d / "long.h5"
    write_capture(rec, render_capture(model, "monochromatic", surfaces, seed=5))
    return {"dir": d, "rec": rec, "ill": ill}


def _batch(recording, store, *extra):
    r = run_cli("batch", recording["rec"], "--illumination", recording["ill"], "--solver", "nearfield",
                "--cache", store, "--json", *extra)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _entries(out):
    res = out["items"][0]["result"]
    return res, [read_record(p, s).data for p, s in ((_path(out, "normals"), "normals"), (_path(out, "depth"), "depth"))]


def _path(out, name):
    return next(p for p in out["items"][0]["result"]["outputs"] if p.endswith(f"{name}.h5"))


@pytest.fixture(scope="module")
def uninterrupted(recording, tmp_path_factory):
    d = tmp_path_factory.mktemp("whole")
    return _batch(recording, d / "store", "--out", d / "out", "--threads", "1")


def test_a_batch_killed_halfway_resumes_and_equals_an_uninterrupted_run(recording, uninterrupted, tmp_path):
    store = tmp_path / "store"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", _KILLED, str(recording["rec"]), str(recording["ill"]), str(store)],
                       env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == -9, r.stderr  # killed, as a user's kill -9 would
    partials = list(store.rglob(".*.partial.h5"))
    assert len(partials) == 2  # normals and depth, neither finished
    claimed = {p.parent.name: max(json.loads(q.read_text())["done"] for q in progress_files(
        p.parent / (p.name.split(".")[1] + ".h5"))) for p in partials}
    both = min(claimed.values())  # frames both entries record (a kill between their records: the fewer)
    assert set(claimed) == {"normals", "depth"} and 16 <= both < FRAMES, claimed
    resumed = _batch(recording, store, "--out", tmp_path / "out", "--threads", "2")
    assert resumed["frames_solved"] == FRAMES - both  # only what the progress files did not claim
    (res, data), (want, wdata) = _entries(resumed), _entries(uninterrupted)
    assert (res["normals_key"], res["depth_key"]) == (want["normals_key"], want["depth_key"])
    assert (res["normals_sha256"], res["depth_sha256"]) == (want["normals_sha256"], want["depth_sha256"])
    for a, b in zip(data, wdata):
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    assert not list(store.rglob(".*.partial.h5")) and not list(store.rglob(".*.progress-*.json"))
    assert os.stat(_path(resumed, "depth")).st_nlink == 2  # --out links the store's file: one copy


def test_frame_ranges_on_two_worker_processes_equal_the_serial_run(recording, uninterrupted, tmp_path):
    pooled = _batch(recording, tmp_path / "store", "--workers", "2", "--threads", "1")
    res, want = pooled["items"][0]["result"], uninterrupted["items"][0]["result"]
    assert (res["normals_sha256"], res["depth_sha256"]) == (want["normals_sha256"], want["depth_sha256"])
    # Frame ranges ran in worker processes (which of the two took how many is the pool's business).
    assert pooled["items"][0]["worker"] and pooled["frames_solved"] == FRAMES
    again = _batch(recording, tmp_path / "store")
    assert again["frames_solved"] == 0 and again["items"][0]["result"]["depth_sha256"] == want["depth_sha256"]


def test_half_precision_is_its_own_entry_and_close_to_single(recording, uninterrupted, tmp_path):
    half = _batch(recording, tmp_path / "store", "--precision", "half", "--out", tmp_path / "out")
    assert half["items"][0]["result"]["normals_key"] != uninterrupted["items"][0]["result"]["normals_key"]
    n16 = read_record(_path(half, "normals"), "normals").data["normals"]
    n32 = read_record(_path(uninterrupted, "normals"), "normals").data["normals"]
    assert n16.dtype == np.float16 and np.abs(n16.astype(np.float32) - n32).max() < 1e-3
    assert half["items"][0]["result"]["normal_mean_error_deg"] == pytest.approx(
        uninterrupted["items"][0]["result"]["normal_mean_error_deg"], abs=0.02)


def test_the_contact_mask_added_later_reads_the_stored_heights(recording, uninterrupted, tmp_path):
    store = tmp_path / "store"
    _batch(recording, store)
    later = _batch(recording, store, "--save", "confidence,contact", "--out", tmp_path / "out")
    assert later["frames_solved"] == 0  # normals and heights read back, not solved again
    contact = read_record(_path(later, "contact"), "contact")
    assert contact.data["contact"].shape == (FRAMES,) + SHAPE and 0 < contact.meta["contact_fraction"] < 0.5


def test_a_truncated_recording_fails_alone(recording, tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(recording["rec"].read_bytes()[:4096])
    r = run_cli("batch", recording["rec"], bad, "--illumination", recording["ill"], "--solver", "nearfield",
                "--cache", tmp_path / "store", "--json")
    assert r.returncode == 1
    out = json.loads(r.stdout)
    assert [i["ok"] for i in out["items"]] == [True, False] and str(bad) in out["items"][1]["error"]
    assert out["frames_per_second"] > 0 and out["peak_rss_mb"] > 0
    assert partial_path(bad).exists() is False


def test_the_device_pipeline_equals_the_cpu_fast_path_on_its_torch_variant(recording):
    """``--device cuda`` runs GPUFramePipeline.solve_device a chunk at a time
    (pipeline.frame_pipeline.device); its torch variant runs on the CPU, so the path is checked here
    against the CPU frame pipeline (the fused CUDA kernel itself: tests/pipeline/normals/test_gpu_nearfield.py,
    on a GPU)."""
    from types import SimpleNamespace

    from pipeline.depth.fast import FastDST
    from pipeline.frame_pipeline import FramePipeline
    from pipeline.frame_pipeline.device import DeviceFramePipeline
    from pipeline.frame_pipeline.gpu_stream import GPUFramePipeline
    from pipeline.solving.frame_solvers import fast_nearfield
    from pipeline.solving.light_files import capture_lights
    from pipeline.streaming.frame_setup import _on_device
    from pipeline.streaming.inputs import read_capture
    from pipeline.streaming.plan import plan_stream

    cap = read_capture(recording["rec"])
    lights = capture_lights(cap, None, read_record(recording["ill"], "illumination"))
    frames = np.asarray(cap.data["frames"][:8])
    dark = cap.data.get("dark")
    gpu = DeviceFramePipeline(GPUFramePipeline(lights.field, PX, dark=dark, solver="torch", device="cpu",
                                               host_threads=1)).run(frames)
    prep = SimpleNamespace(region=None, dark=dark, shape=SHAPE)
    with FramePipeline(fast_nearfield(lights, prep), FastDST(SHAPE, PX), threads=1) as pipe:
        cpu = pipe.run(frames)
    both = gpu.mask & cpu.mask
    assert both.mean() > 0.9 and (gpu.mask == cpu.mask).mean() > 0.999
    np.testing.assert_allclose(gpu.normals[both], cpu.normals[both], atol=2e-4)
    np.testing.assert_allclose(gpu.height, cpu.height, atol=2e-3 * np.abs(cpu.height).max())
    job, _, _ = plan_stream(recording["rec"], illumination=recording["ill"], solver="nearfield", device="cuda",
                            store=recording["dir"] / "plan-only")
    assert _on_device(job, lights, cap.data["frames"])  # what --device cuda would run
    job.options["solver"] = "lut"
    assert not _on_device(job, lights, cap.data["frames"])
