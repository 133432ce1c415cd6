"""iristac bench compare: slower or less accurate beyond the noise of the repeats, nothing else."""

import json

from helpers import run_cli
from pipeline.bench.compare import compare_runs


def _run(machine="m", **rows):
    return {"machine": machine, "sections": [{"bench": "live", "rows": [
        dict(knob="k", setting=name, **fields) for name, fields in rows.items()]}]}


def _kinds(res):
    return {(c.setting, c.kind) for c in res["changes"]}


def test_slower_beyond_the_spread_of_the_repeats_is_flagged_within_it_not():
    old = _run(steady={"seconds": 1.0, "seconds_runs": [1.0, 1.01, 1.02], "error": 1.0},
               noisy={"seconds": 1.0, "seconds_runs": [1.0, 1.3, 1.4], "error": 1.0},
               unrepeated={"seconds": 1.0, "error": 1.0})
    new = _run(steady={"seconds": 1.2, "seconds_runs": [1.2, 1.21, 1.22], "error": 1.0},
               noisy={"seconds": 1.5, "seconds_runs": [1.5, 1.6, 1.9], "error": 1.0},  # within 2 x 30 %
               unrepeated={"seconds": 1.2, "error": 1.0})  # within the 25 % tolerance
    res = compare_runs(old, new)
    assert _kinds(res) == {("steady", "slower")} and res["regressions"] == 1
    c = res["changes"][0]
    assert c.threshold == 0.10 and "floor" in c.noise


def test_error_growth_beyond_the_floor_is_flagged_round_off_and_seed_noise_are_not():
    old = _run(a={"seconds": 1.0, "error": 1.0}, tiny={"seconds": 1.0, "error": 1e-14},
               seeded={"seconds": 1.0, "error": 0.5, "error_runs": [0.3, 0.5, 0.7]},
               better={"seconds": 1.0, "error": 1.0})
    new = _run(a={"seconds": 1.0, "error": 1.05}, tiny={"seconds": 1.0, "error": 5e-14},
               seeded={"seconds": 1.0, "error": 0.6}, better={"seconds": 1.0, "error": 0.5})
    assert _kinds(compare_runs(old, new)) == {("a", "less accurate"), ("better", "more accurate")}


def test_times_of_different_machines_are_not_compared_unless_asked(tmp_path):
    old = _run("machine A", x={"seconds": 1.0, "seconds_runs": [1.0, 1.0], "error": 1.0})
    new = _run("machine B", x={"seconds": 3.0, "seconds_runs": [3.0, 3.0], "error": 1.0})
    assert compare_runs(old, new)["changes"] == [] and not compare_runs(old, new)["times_compared"]
    assert _kinds(compare_runs(old, new, across_machines=True)) == {("x", "slower")}
    (tmp_path / "old.json").write_text(json.dumps(old))
    (tmp_path / "new.json").write_text(json.dumps(new))
    r = run_cli("bench", "compare", tmp_path / "old.json", tmp_path / "new.json")
    assert r.returncode == 0 and "times not compared" in r.stdout, r.stderr
    r = run_cli("bench", "compare", tmp_path / "old.json", tmp_path / "new.json", "--across-machines")
    assert r.returncode == 1 and "REGRESSION  slower" in r.stdout and "k: x: 1 s -> 3 s: 3.00x slower" in r.stdout
    r = run_cli("bench", "compare", tmp_path / "old.json", tmp_path / "missing.json")
    assert r.returncode == 2 and "missing.json: no such file" in r.stderr
