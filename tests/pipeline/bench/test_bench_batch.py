"""``iristac bench batch`` runs end to end (--quick: the LUT on two short 160 x 120 recordings) and
prints its table with the targets; the figures themselves are measured by the benchmark, never
asserted here."""

import json

from helpers import run_cli


def test_bench_batch_quick_measures_batch_beside_live_and_states_its_targets(tmp_path):
    r = run_cli("bench", "batch", "--quick", "--lengths", "24", "48", "--cache", tmp_path / "store", "--json",
                timeout=600)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    rows = [m for m in res["measurements"] if not m.get("workers")]
    assert {(m["frames"], m["threads"]) for m in rows} == {(n, t) for n in (24, 48) for t in sorted({1, res["cores"]})}
    for m in rows:
        assert m["fps"] > 0 and m["live_fps"] > 0 and m["peak_rss_mb"] > 0 and m["frames"] in (24, 48)
    assert rows[0]["error_deg"] is not None  # the shortest recording carries the rendered truth
    assert any("peak memory" in t["what"] for t in res["targets"])
    pooled = [m for m in res["measurements"] if m.get("workers")]
    if res["cores"] > 1:  # the longest recording again on one worker process, then on one a core
        assert [m["workers"] for m in pooled] == [1, res["cores"]] and all(m["fps"] > 0 for m in pooled)
        assert any("local workers" in t["what"] for t in res["targets"])
    assert res["rows"] and all(row["knob"].startswith("batch lut @") for row in res["rows"])
    from pipeline.bench.batch import format_table

    table = format_table(res)
    assert "batch/live" in table and "target lut peak memory" in table
