"""``iristac run``: caching across runs, what a change recomputes, --force, bad inputs (real files, subprocess CLI)."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import pytest
import yaml

from helpers import REPO, run_cli
from pipeline.base.errors import UserError
from pipeline.base.store import StageStore
from pipeline.workflows.run import plan_pipeline, run_pipeline

STAGES = ["synthesize", "calibrate", "capture", "normals", "depth"]

# Small enough for a shared 2-core machine, but every stage is the real one.
SMALL = {
    "cache": "cache",
    "synthesize": {"model": "bare_ring", "height": 32, "width": 40, "mm_per_px": 0.35},
    "calibrate": {"render": {"presses": 4, "depth_mm": 0.6, "spread_mm": 3.0}, "ball_radius_mm": 3.0,
                  "model": "far", "folds": 2},
    "capture": {"render": True, "contacts": 1, "size_mm": 2.5, "depth_mm": 0.5},
    "normals": {"solver": "lstsq"},
    "depth": {"integrator": "dst"},
}


def write_config(path: Path, cfg: dict) -> Path:
    path.write_text(yaml.safe_dump(cfg), encoding="utf-8")
    return path


def run_json(*args) -> tuple[dict, float]:
    t0 = time.perf_counter()
    r = run_cli("run", *args, "--json")
    seconds = time.perf_counter() - t0
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout), seconds


def by_name(report: dict) -> dict:
    return {s["name"]: s for s in report["stages"]}


def test_second_run_hits_the_cache_for_all_five_stages(tmp_path):
    # The capture goes through the ring emulator on a pty and the rendering virtual camera.
    cfg = {**SMALL, "out": "out",
           "capture": {"emulate": True, "virtual_camera": True, "contacts": 1, "size_mm": 2.5, "fps": 200.0}}
    config = write_config(tmp_path / "run.yaml", cfg)
    first, t_first = run_json(config)
    second, t_second = run_json(config)
    assert [s["name"] for s in first["stages"]] == STAGES
    assert [s["cached"] for s in first["stages"]] == [False] * 5
    assert [s["cached"] for s in second["stages"]] == [True] * 5
    assert [s["key"] for s in first["stages"]] == [s["key"] for s in second["stages"]]
    assert set(first["stages"][0]) >= {"name", "cached", "seconds", "key"}
    stage_first = sum(s["seconds"] for s in first["stages"])
    stage_second = sum(s["seconds"] for s in second["stages"])
    print(f"\nfirst run {t_first:.2f} s wall, {first['seconds']:.2f} s in run_pipeline (stages {stage_first:.2f} s); "
          f"second run {t_second:.2f} s wall, {second['seconds']:.2f} s in run_pipeline (stages {stage_second:.3f} s)")
    assert stage_second < 0.2 * stage_first
    # Generous: on a loaded machine imports and interpreter start-up dominate the cached run.
    assert second["seconds"] < 0.5 * first["seconds"]
    # The emulated capture carries truth, so the run reports real errors, and the outputs exist.
    assert first["summary"]["normal_mean_error_deg"] == second["summary"]["normal_mean_error_deg"]
    assert 0 < first["summary"]["normal_mean_error_deg"] < 45
    assert (tmp_path / "out" / "depth.h5").is_file() and (tmp_path / "out" / "run.json").is_file()
    assert StageStore(tmp_path / "cache").verify() == []


@pytest.fixture(scope="module")
def seeded(tmp_path_factory):
    """The SMALL config run once; tests get a copy of its store."""
    d = tmp_path_factory.mktemp("seeded")
    config = write_config(d / "run.yaml", SMALL)
    first = run_pipeline(config, progress=False)
    assert [s["cached"] for s in first.stages] == [False] * 5
    return d


@pytest.fixture
def small(seeded, tmp_path):
    shutil.copytree(seeded / "cache", tmp_path / "cache")
    config = shutil.copy(seeded / "run.yaml", tmp_path / "run.yaml")
    # The run manifest (why a stage reruns) is per config path: record this one's.
    assert all(s["cached"] for s in run_pipeline(config, progress=False).stages)
    return Path(config)


def cached_flags(report) -> dict:
    return {s["name"]: s["cached"] for s in report.stages}


def test_a_changed_parameter_recomputes_that_stage_and_downstream_only(small):
    cfg = dict(SMALL, depth={"integrator": "fc"})
    write_config(small, cfg)
    plan = {p["name"]: p for p in plan_pipeline(small)}
    assert plan["depth"]["reason"] == "parameters changed (integrator: 'dst' -> 'fc')"
    assert [p["cached"] for p in plan.values()] == [True, True, True, True, False]
    assert cached_flags(run_pipeline(small, progress=False)) == dict(zip(STAGES, [True] * 4 + [False]))

    cfg = dict(cfg, normals={"solver": "robust"})
    write_config(small, cfg)
    plan = {p["name"]: p for p in plan_pipeline(small)}
    assert plan["normals"]["reason"].startswith("parameters changed (solver: 'lstsq' -> 'robust')")
    assert plan["depth"]["reason"] == "input stage 'normals' will be recomputed"
    assert cached_flags(run_pipeline(small, progress=False)) == dict(zip(STAGES, [True] * 3 + [False] * 2))

    # Writing a default out explicitly changes nothing.
    cfg = dict(cfg, capture={**SMALL["capture"], "mode": "monochromatic", "seed": 0})
    write_config(small, cfg)
    assert all(p["cached"] for p in plan_pipeline(small))


def test_force_recomputes_the_stage_and_what_depends_on_it(small):
    r = run_cli("run", small, "--force", "capture", "--json")
    assert r.returncode == 0, r.stderr
    flags = {s["name"]: (s["cached"], s["reason"]) for s in json.loads(r.stdout)["stages"]}
    assert flags == {"synthesize": (True, "cached"), "calibrate": (True, "cached"), "capture": (False, "forced"),
                     "normals": (False, "downstream of a forced stage"),
                     "depth": (False, "downstream of a forced stage")}
    dry = run_cli("run", small, "--dry-run", "--force", "depth")
    assert dry.returncode == 0, dry.stderr
    assert [line.split()[:2] for line in dry.stdout.splitlines()] == [
        ["synthesize", "cached"], ["calibrate", "cached"], ["capture", "cached"], ["normals", "cached"],
        ["depth", "RUN"]]
    with pytest.raises(UserError, match="--force: unknown stage 'dept'"):
        plan_pipeline(small, force=["dept"])


def test_unknown_config_key_is_one_line_naming_key_and_allowed_keys(tmp_path):
    config = write_config(tmp_path / "run.yaml", {**SMALL, "normals": {"solvr": "lstsq"}})
    r = run_cli("run", config)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "unknown key 'solvr' at normals" in lines[0] and "allowed keys:" in lines[0] and "solver" in lines[0]
    assert str(config) in lines[0]
    assert not (tmp_path / "cache").exists()  # nothing ran


def test_corrupt_capture_file_fails_in_one_line_and_keeps_earlier_stages(tmp_path):
    bad = tmp_path / "capture.h5"
    bad.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 200)  # an HDF5 signature, then garbage
    cfg = {"cache": "cache", "synthesize": SMALL["synthesize"], "capture": {"file": "capture.h5"},
           "normals": {"lights": "illumination"}, "depth": {}}
    config = write_config(tmp_path / "run.yaml", cfg)
    r = run_cli("run", config, "--json")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("iristac run: error: stage 'capture' failed:"), r.stderr
    assert str(bad) in lines[0]
    ran = json.loads(r.stdout)  # --json still says what ran before the failure
    assert [(s["name"], s["cached"], "error" in s) for s in ran["stages"]] == [
        ("synthesize", False, False), ("capture", False, True)]
    assert str(bad) in ran["error"]
    plan = {p["name"]: p["cached"] for p in plan_pipeline(config)}
    assert plan == {"synthesize": True, "capture": False, "normals": False, "depth": False}


def test_capture_file_is_keyed_by_content(tmp_path):
    from pipeline.base.capture import write_capture
    from sim.contacts import contact_surfaces
    from sim.render import bare_ring_illumination
    from sim.rendered_capture import render_capture

    model = bare_ring_illumination((24, 30), 0.35)
    cap_path = tmp_path / "capture.h5"
    surfaces = contact_surfaces("sphere", model.shape, model.mm_per_px, 1, size_mm=2.0)
    write_capture(cap_path, render_capture(model, "monochromatic", surfaces, seed=1))
    cfg = {"cache": "cache", "synthesize": {"model": "bare_ring", "height": 24, "width": 30, "mm_per_px": 0.35},
           "capture": {"file": "capture.h5"}, "normals": {"solver": "nearfield"}, "depth": {}}
    config = write_config(tmp_path / "run.yaml", cfg)
    first = run_pipeline(config, progress=False)
    assert first.summary["normal_mean_error_deg"] < 5  # the exact illumination it was rendered with
    # Same content, other name: still cached. Other content: capture and downstream recompute.
    cap_path.rename(tmp_path / "moved.h5")
    write_config(config, {**cfg, "capture": {"file": "moved.h5"}})
    assert all(p["cached"] for p in plan_pipeline(config))
    write_capture(tmp_path / "moved.h5", render_capture(model, "monochromatic", surfaces, seed=2))
    plan = {p["name"]: (p["cached"], p["reason"]) for p in plan_pipeline(config)}
    assert plan["capture"] == (False, "an input changed")
    assert [plan[s][0] for s in ("synthesize", "normals", "depth")] == [True, False, False]


def test_example_config_is_valid_and_plans_all_five_stages(tmp_path):
    plan = plan_pipeline(REPO / "examples" / "pipeline.yaml", cache=tmp_path / "cache")
    assert [p["name"] for p in plan] == STAGES
    assert not any(p["cached"] for p in plan)


def test_missing_section_a_stage_needs_is_named(tmp_path):
    config = write_config(tmp_path / "run.yaml", {"capture": {"render": True}, "normals": {}})
    with pytest.raises(UserError, match="stage 'capture' with a virtual sensor needs the 'synthesize' section"):
        plan_pipeline(config)


def test_failing_calibration_names_the_config_fields_and_keeps_synthesize(tmp_path):
    from pipeline.stages.graph import StageFailed

    cfg = {**SMALL, "calibrate": {"render": {"presses": 3, "depth_mm": 0.01}, "ball_radius_mm": 3.0}}
    config = write_config(tmp_path / "run.yaml", cfg)
    with pytest.raises(StageFailed) as info:
        run_pipeline(config, progress=False)
    msg = str(info.value)
    assert msg.startswith("stage 'calibrate' failed: the sphere capture rendered from calibrate.render: calibration refused: only")
    assert "calibrate.render: presses, depth_mm" in msg and "iristac-calibrate-" not in msg
    assert [(r.name, r.error is None) for r in info.value.results] == [("synthesize", True), ("calibrate", False)]
    assert [p["cached"] for p in plan_pipeline(config)] == [True, False, False, False, False]


def test_rendered_calibration_follows_the_capture_files_lighting_mode(tmp_path):
    from pipeline.base.capture import write_capture
    from pipeline.stages.config import resolve_config
    from sim.contacts import contact_surfaces
    from sim.render import bare_ring_illumination
    from sim.rendered_capture import render_capture

    model = bare_ring_illumination((12, 16), 0.5)
    write_capture(tmp_path / "c.h5", render_capture(model, "trichromatic", contact_surfaces("sphere", (12, 16), 0.5, 2, size_mm=3.0)))
    cfg = resolve_config({"calibrate": {"render": {}}, "capture": {"file": "c.h5"}}, tmp_path)
    assert cfg["calibrate"]["render"]["mode"] == "trichromatic"
    cfg = resolve_config({"calibrate": {"render": {}}, "capture": {"render": True, "mode": "point"}}, tmp_path)
    assert cfg["calibrate"]["render"]["mode"] == "point"


def test_traced_synthesize_is_keyed_by_the_scene_content(tmp_path):
    scene = (REPO / "sim" / "scenes" / "default.yaml").read_text(encoding="utf-8")
    (tmp_path / "scene.yaml").write_text(scene, encoding="utf-8")
    cfg = {"cache": "cache", "synthesize": {"model": "traced", "scene": "scene.yaml", "rays": 4096,
                                            "height": 6, "width": 8, "mm_per_px": 2.0}}
    config = write_config(tmp_path / "run.yaml", cfg)
    report = run_pipeline(config, progress=False)
    from pipeline.base.store import read_record

    assert report.stages[0]["cached"] is False
    ill = read_record(report.stages[0]["path"], schema="illumination")
    assert ill.data["V"].shape == (24, 6, 8, 3) and ill.meta["rays_per_source"] == 4096
    # Renamed, or reworded: same light, cached. A changed LED ring radius: traced again.
    (tmp_path / "scene.yaml").rename(tmp_path / "renamed.yaml")
    (tmp_path / "renamed.yaml").write_text(scene.replace("description: >-", "description: >-\n  Reworded."),
                                           encoding="utf-8")
    write_config(config, {**cfg, "synthesize": {**cfg["synthesize"], "scene": "renamed.yaml"}})
    assert plan_pipeline(config)[0]["cached"]
    (tmp_path / "renamed.yaml").write_text(scene.replace("radius: 40.0 ", "radius: 39.0 "), encoding="utf-8")
    plan = plan_pipeline(config)[0]
    assert not plan["cached"] and plan["reason"].startswith("parameters changed (scene:")
