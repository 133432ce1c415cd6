"""One key per piece of work: the same work through two entry points is one cache entry, and
every parameter that changes a stage's result changes its key (real CLI, real files)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from helpers import run_cli
from pipeline.base.store import StageStore, read_record
from pipeline.stages import STAGE_ORDER, stage_module

# Small and fast, every stage the real one; the capture has truth.
CONFIG = {
    "synthesize": {"model": "bare_ring", "height": 20, "width": 24, "mm_per_px": 0.4},
    "capture": {"render": True, "contacts": 1, "size_mm": 2.0, "depth_mm": 0.4},
    "normals": {"solver": "nearfield"},
    "depth": {"integrator": "dst"},
}


def entries(cache: Path, stage: str) -> list[Path]:
    return sorted((cache / stage).glob("*.h5"))


def run_config(tmp_path: Path, cfg: dict, cache: Path) -> dict:
    config = tmp_path / "run.yaml"
    config.write_text(yaml.safe_dump(cfg), encoding="utf-8")
    r = run_cli("run", config, "--cache", cache, "--json")
    assert r.returncode == 0, r.stderr
    return {s["name"]: s for s in json.loads(r.stdout)["stages"]}


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """``iristac run`` once on a shared cache; tests work on copies of nothing: they only add."""
    d = tmp_path_factory.mktemp("keys")
    cache = d / "cache"
    return d, cache, run_config(d, CONFIG, cache)


def test_reconstruct_of_runs_results_is_runs_entry_not_a_second_one(ran, tmp_path):
    """The depth stage was keyed {integrator} by run and {integrator, mm_per_px} by
    reconstruct: the same work was two entries. Now both key it alike."""
    _, cache, stages = ran
    cap = cache / "capture" / f"{stages['capture']['key']}.h5"
    ill = cache / "synthesize" / f"{stages['synthesize']['key']}.h5"
    r = run_cli("reconstruct", cap, "--illumination", ill, "--solver", "nearfield", "--cache", cache,
                "--out", tmp_path / "out", "--no-images", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["cached"] is True
    assert [p.stem for p in entries(cache, "normals")] == [stages["normals"]["key"]]
    assert [p.stem for p in entries(cache, "depth")] == [stages["depth"]["key"]]
    # The depth key holds the pitch the heights are scaled by, from both entry points.
    depth = read_record(entries(cache, "depth")[0], schema="depth")
    assert json.loads(depth.provenance["iristac_params"]) == {"integrator": "dst", "mm_per_px": 0.4}


def test_a_capture_file_is_one_entry_through_run_reconstruct_and_batch(ran, tmp_path):
    d, cache, stages = ran
    ill = cache / "synthesize" / f"{stages['synthesize']['key']}.h5"
    cap_file = tmp_path / "recording.h5"
    cap_file.write_bytes((cache / "capture" / f"{stages['capture']['key']}.h5").read_bytes())
    # reconstruct first, on the standalone file: computes.
    r = run_cli("reconstruct", cap_file, "--illumination", ill, "--solver", "nearfield", "--cache", tmp_path / "c2",
                "--out", tmp_path / "out", "--no-images", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["cached"] is False
    # run with the same file as its capture section: the same keys, all cached.
    cfg = {**copy.deepcopy(CONFIG), "capture": {"file": str(cap_file)}}
    keys = run_config(tmp_path, cfg, tmp_path / "c2")
    assert [keys[s]["cached"] for s in ("capture", "normals", "depth")] == [False, True, True]
    # batch on the same file: the same normals and depth keys, nothing new in the store.
    r = run_cli("batch", cap_file, "--illumination", ill, "--solver", "nearfield", "--cache", tmp_path / "c2",
                "--json")
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)["items"][0]["result"]
    assert (result["normals_key"], result["depth_key"]) == (keys["normals"]["key"], keys["depth"]["key"])
    assert len(entries(tmp_path / "c2", "normals")) == 1 and len(entries(tmp_path / "c2", "depth")) == 1


def test_the_demos_trace_and_runs_trace_are_one_entry(tmp_path):
    from pipeline.stages import synthesize
    from pipeline.workflows.run import plan_pipeline

    store = StageStore(tmp_path / "cache")
    _, key, cached = synthesize.run(store, "default", (6, 8), 2.0, rays=4096, sampler="sobol")
    assert not cached
    config = tmp_path / "run.yaml"
    config.write_text(yaml.safe_dump({"cache": "cache", "synthesize": {
        "model": "traced", "scene": "default", "rays": 4096, "sampler": "sobol", "height": 6, "width": 8,
        "mm_per_px": 2.0}}), encoding="utf-8")
    plan = plan_pipeline(config)
    assert plan[0]["key"] == key.digest and plan[0]["cached"]


# --- every result-changing parameter changes the key ------------------------------------------

def _key(stage: str, params: dict, inputs=("in",)) -> str:
    return stage_module(stage).SPEC.key(StageStore("unused"), params, list(inputs)).digest


def _variants(base: dict, changes: dict) -> list[tuple[str, dict]]:
    out = []
    for name, value in changes.items():
        p = copy.deepcopy(base)
        p[name] = value
        out.append((name, p))
    return out


#: Per stage: (a base section, {parameter: another value that changes the result}).
KEY_CASES = {
    "synthesize": (dict(scene="default", height=6, width=8, mm_per_px=2.0, rays=4096, sampler="sobol", seed=0,
                        method="hits"),
                   dict(height=7, width=9, mm_per_px=1.5, rays=4097, sampler="grid", seed=1, method="image",
                        dtype="float64", exposure=2.0, drive=np.ones((1, 24, 3)), brightness=np.ones(1),
                        gains=np.ones(24))),
    "calibrate": ({"capture": "s.h5", "ball_radius_mm": 2.0, "mm_per_px": None, "model": "far", "folds": 5},
                  dict(ball_radius_mm=2.5, mm_per_px=0.1, model="near", folds=4,
                       render={"presses": 8, "depth_mm": 0.6, "spread_mm": 4.0, "noise_dn": 1.0, "target_dn": 200.0,
                               "seed": 0, "mode": "point"})),
    "capture": ({**stage_module("capture").SPEC.defaults, "render": True},
                dict(mode="point", object="cylinder", size_mm=2.0, depth_mm=0.3, contacts=3, spread_mm=1.0,
                     noise_dn=2.0, target_dn=150.0, seed=4)),
    "normals": (dict(solver="lstsq", ratio=False, max_condition=1e3, dtype="float32", lights="illumination"),
                dict(solver="robust", ratio=True, max_condition=100.0, dtype="float64", lights="calibration",
                     mask=np.eye(3, dtype=bool), markers=np.eye(3, dtype=bool), drift="none")),
    "depth": (dict(integrator="dst", mm_per_px=0.1), dict(integrator="sparse", mm_per_px=0.2)),
}


def _params(stage: str):
    """(make key parameters from section overrides, {parameter: another value that changes the
    result}); an unknown stage is an error, never another stage's parameters."""
    if stage not in KEY_CASES:
        raise KeyError(f"no key-parameter case for stage {stage!r}: add one to KEY_CASES")
    base, changes = KEY_CASES[stage]
    s = stage_module(stage)
    return (lambda **kw: s.params({**base, **kw})), changes


def test_every_stage_has_a_key_case_and_an_unknown_one_fails():
    assert set(KEY_CASES) == set(STAGE_ORDER)
    with pytest.raises(KeyError, match="no key-parameter case"):
        _params("nostage")


@pytest.mark.parametrize("stage", STAGE_ORDER)
def test_every_parameter_that_changes_the_result_changes_the_key(stage):
    make, changes = _params(stage)
    base = _key(stage, make())
    assert _key(stage, make()) == base  # deterministic
    for name, value in changes.items():
        assert _key(stage, make(**{name: value})) != base, f"{stage}: changing {name} left the key unchanged"
    assert _key(stage, make(), inputs=("other",)) != base, f"{stage}: another input left the key unchanged"


def test_the_capture_stage_keys_each_source_by_what_it_reads():
    cap = stage_module("capture")
    d = cap.SPEC.defaults
    emulated = cap.params({**d, "emulate": True, "virtual_camera": True})
    for name, value in dict(fps=50.0, faults="drop=0.1", frames_per_pattern=2, object="indenters").items():
        assert cap.params({**d, "emulate": True, "virtual_camera": True, name: value}) != emulated, name
    hardware = cap.params({**d, "port": "/dev/ttyACM0", "camera": 0})
    for name, value in dict(port="/dev/ttyACM1", camera=1, mm_per_px=0.2, frames_per_pattern=3).items():
        assert cap.params({**d, "port": "/dev/ttyACM0", "camera": 0, name: value}) != hardware, name


def test_a_traced_scene_is_keyed_by_its_content_not_its_name_or_words():
    from dataclasses import replace

    from pipeline.stages.synthesize import params
    from sim.scene import load_scene

    scene = load_scene("default")
    def key_of(sc):
        return _key("synthesize", params({"scene": sc, "height": 6, "width": 8, "mm_per_px": 2.0}))

    key = key_of(scene)
    assert key_of(replace(scene, description="other words", source="elsewhere.yaml")) == key
    assert key_of(replace(scene, plane=replace(scene.plane, z=scene.plane.z + 1.0))) != key
