"""``iristac bench render`` runs and reports fps and error per effect set (smoke test, no timing asserted)."""

import argparse

from pipeline.bench import render as bench


def test_bench_render_quick_smoke():
    args = argparse.Namespace(quick=True, seconds=0.0, device="cpu", threads=1, json=True)
    res = bench.run(args)
    sets = {r["setting"] for r in res["rows"] if r["knob"].startswith("render")}
    assert sets == set(bench.EFFECT_SETS)
    for r in res["rows"]:
        assert r["fps"] > 0 and r["seconds"] > 0 and r["error"] >= 0
        if r["knob"].startswith("render"):
            assert r["error"] < 0.01  # float32 frames agree with float64 to a hundredth of a DN
    assert "fps" in bench.format_table(res)
