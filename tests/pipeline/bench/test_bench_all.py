"""iristac bench all: one report, rows with the machine, and a plot (run on the cheapest benchmark: render, 10 s quick)."""

import json

from helpers import run_cli
from pipeline.bench.all import common_rows
from pipeline.bench.report import format_markdown


def test_bench_all_writes_markdown_json_and_plot(tmp_path):
    md, png = tmp_path / "b.md", tmp_path / "b.png"  # no --plot: the figure goes beside the report
    r = run_cli("bench", "all", "--quick", "--only", "render", "--out", md, "--json", timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    rows = res["sections"][0]["rows"]
    assert rows and all(row["machine"] == res["machine"] and "cores" in row["machine"] for row in rows)
    text = md.read_text()
    assert "| knob | setting | error | seconds | machine |" in text and res["machine"] in text
    assert png.stat().st_size > 1000 and json.loads(md.with_suffix(".json").read_text())["machine"] == res["machine"]


def test_sectioned_sim_results_become_common_rows():
    result = {"rays_sampler": {"rows": [{"sampler": "sobol", "rays": 1000, "image_error": 0.2, "seconds": 0.1}]},
              "newton": {"rows": [{"dtype": "float32", "method": "paper", "iterations": 1,
                                   "median_error_mm": float("nan"), "seconds": 0.01}]}}
    rows = common_rows("sim", result)
    assert rows[0] == {"knob": "rays x sampler", "setting": "sobol 1,000", "error": 0.2,
                       "error_unit": "rel. L2 vs reference", "seconds": 0.1, "sampler": "sobol", "rays": 1000}
    assert rows[1]["error"] is None  # NaN (no converged hit) is reported as no number, not NaN
    md = format_markdown({"machine": "m", "sections": [{"bench": "sim", "seconds": 1.0, "error": None,
                                                        "rows": [dict(r, machine="m") for r in rows],
                                                        "table": "raw table"}]})
    assert "| rays x sampler | sobol 1,000 | 0.2 rel. L2 vs reference | 0.1 | m |" in md and "raw table" in md
