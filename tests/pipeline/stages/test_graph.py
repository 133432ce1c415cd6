"""The stage graph engine: caching, reasons, --force, failures that keep earlier results."""

from pathlib import Path

import numpy as np
import pytest

from pipeline.base.errors import UserError
from pipeline.base.identity import file_input_key
from pipeline.base.store import Record, StageStore
from pipeline.stages.graph import Stage, StageFailed, plan_stages, run_stages


def _chain(calls, scale=1.0, fail_at=None):
    """A real three-stage chain: a capture-like array, its normals, its depth."""

    def capture(inputs):
        calls.append("capture")
        frames = (np.arange(2 * 1 * 4 * 5 * 3).reshape(2, 1, 4, 5, 3) % 200).astype(np.uint8)
        return Record("capture", {"frames": frames, "reference": frames[0], "drive": np.ones((1, 24, 3), np.float32),
                                  "brightness": np.ones(1, np.float32)},
                      {"mm_per_px": 0.1, "pattern_names": ["p0"], "source": "test"})

    def normals(inputs):
        calls.append("normals")
        if fail_at == "normals":
            raise ValueError("bad light matrix in calibration.h5")
        f = inputs["capture"].data["frames"].astype(np.float32)[:, 0]
        n = np.zeros(f.shape[:3] + (3,), np.float32)
        n[..., 2] = 1.0
        n[..., 0] = scale * f[..., 0] / 255.0
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        return Record("normals", {"normals": n, "mask": np.ones(f.shape[:3], bool)}, {"solver": "lstsq"})

    def depth(inputs):
        calls.append("depth")
        n = inputs["normals"].data["normals"]
        h = np.cumsum(-n[..., 0] / n[..., 2], axis=2).astype(np.float32) * 0.1
        return Record("depth", {"height": h, "mask": np.ones(h.shape, bool)}, {"integrator": "fc", "mm_per_px": 0.1})

    return [
        Stage("capture", 1, {"mode": "point"}, [], capture),
        Stage("normals", 1, {"solver": "lstsq", "scale": scale}, ["capture"], normals),
        Stage("depth", 1, {"integrator": "fc"}, ["normals"], depth),
    ]


def test_second_run_hits_the_cache_for_every_stage(tmp_path):
    store, calls = StageStore(tmp_path), []
    first = run_stages(_chain(calls), store, run_name="t")
    second = run_stages(_chain(calls), store, run_name="t")
    assert [r.cached for r in first] == [False, False, False]
    assert [r.cached for r in second] == [True, True, True]
    assert calls == ["capture", "normals", "depth"]
    assert [r.key for r in first] == [r.key for r in second]


def test_parameter_change_recomputes_downstream_only_and_says_why(tmp_path):
    store, calls = StageStore(tmp_path), []
    run_stages(_chain(calls), store, run_name="t")
    plan = plan_stages(_chain([], scale=2.0), store, run_name="t")
    assert [(p.stage.name, p.cached) for p in plan] == [("capture", True), ("normals", False), ("depth", False)]
    assert plan[1].reason == "parameters changed (scale: 1.0 -> 2.0)"
    assert plan[2].reason == "input stage 'normals' will be recomputed"
    calls.clear()
    run_stages(_chain(calls, scale=2.0), store, run_name="t")
    assert calls == ["normals", "depth"]


def test_force_recomputes_a_stage_and_what_depends_on_it(tmp_path):
    store, calls = StageStore(tmp_path), []
    run_stages(_chain(calls), store)
    calls.clear()
    res = run_stages(_chain(calls), store, force=["normals"])
    assert calls == ["normals", "depth"] and [r.cached for r in res] == [True, False, False]
    assert [r.reason for r in res] == ["cached", "forced", "downstream of a forced stage"]
    with pytest.raises(UserError, match="unknown stage 'nromals'"):
        plan_stages(_chain([]), store, force=["nromals"])


def test_failing_stage_keeps_earlier_results_and_names_the_problem(tmp_path):
    store, calls = StageStore(tmp_path), []
    with pytest.raises(StageFailed) as e:
        run_stages(_chain(calls, fail_at="normals"), store, run_name="t")
    assert e.value.stage == "normals" and "calibration.h5" in str(e.value)
    assert [r.name for r in e.value.results] == ["capture", "normals"] and e.value.results[1].error
    calls.clear()
    res = run_stages(_chain(calls), store, run_name="t")
    assert calls == ["normals", "depth"] and res[0].cached


def test_corrupt_cached_entry_is_recomputed_or_with_no_heal_reported(tmp_path):
    store, calls = StageStore(tmp_path), []
    res = run_stages(_chain(calls), store)
    open(res[1].path, "wb").write(b"junk")
    with pytest.raises(StageFailed, match="truncated or corrupt"):
        run_stages(_chain(calls), store, heal=False)
    calls.clear()
    healed = run_stages(_chain(calls), store)
    assert calls == ["normals"] and [r.cached for r in healed] == [True, False, True]
    assert len(list(Path(res[1].path).parent.glob("*.bad-*.h5"))) == 1  # quarantined, not deleted


def test_cycles_and_unknown_dependencies_are_rejected(tmp_path):
    def noop(inputs):
        return None

    with pytest.raises(ValueError, match="cycle"):
        plan_stages([Stage("a", 1, {}, ["b"], noop, schema="depth"), Stage("b", 1, {}, ["a"], noop, schema="depth")],
                    StageStore(tmp_path))
    with pytest.raises(ValueError, match="unknown stage 'zz'"):
        plan_stages([Stage("a", 1, {}, ["zz"], noop, schema="depth")], StageStore(tmp_path))


def test_file_input_key_follows_content(tmp_path):
    p = tmp_path / "cap.h5"
    p.write_bytes(b"abc")
    k1 = file_input_key(p)
    p.write_bytes(b"abd")
    assert k1 != file_input_key(p)
    with pytest.raises(UserError, match="no such file"):
        file_input_key(tmp_path / "missing.h5")
