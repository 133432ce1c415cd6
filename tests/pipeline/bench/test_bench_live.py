"""``iristac bench live`` runs end to end (tiny frames) and prints every verdict; the figures
themselves are measured by the benchmark, never asserted here. The networks (conv, conv-fast)
are left out: their calibrations take minutes, the benchmark's to time, not the suite's."""

import json

from helpers import run_cli


def test_bench_live_smoke(tmp_path):
    r = run_cli("bench", "live", "--quick", "--sizes", "64x48", "--repeats", "1", "--no-startup", "--cache", tmp_path / "c",
                "--models", "lut", "mlp", "--json", timeout=600)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    got = {(m["solver"], m["path"]) for m in res["measurements"]}
    assert {("nearfield", "eager"), ("nearfield", "fast"), ("lut", "fast"), ("mlp", "fast")} <= got
    fast = [m for m in res["measurements"] if m["path"] == "fast"]
    # The fast paths reproduce the eager solvers (the tests pin this; here: through the benchmark).
    assert all(m["deviation_deg"] < 1e-3 for m in fast), fast
    assert res["rows"] and all({"knob", "setting", "error", "error_unit", "seconds"} <= set(row) for row in res["rows"])
    # The text the command prints without --json is this table of the same result.
    from pipeline.bench.live import format_table

    assert "vs eager" in format_table(res)
