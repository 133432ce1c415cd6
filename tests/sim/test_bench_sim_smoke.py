"""``iristac bench sim`` runs every accuracy-vs-time section for real (quick sizes): a section
that breaks (e.g. after a refactor of the tracer's return types) fails here, not in ``bench all``."""

import json

from helpers import run_cli


def test_bench_sim_sections_run_and_report_errors_beside_times():
    r = run_cli("bench", "sim", "--quick", "--only", "rays,flux,newton,multi,effects", "--repeats", "1", "--json",
                timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert {"rays_sampler", "flux", "newton", "multi_source", "effects"} <= set(out)
    # the lens designer's flux error falls with rays; the brief's rays and sampler are the default
    sobol = sorted((x["rays"], x["flux_error_pct"]) for x in out["flux"]["rows"] if x["sampler"] == "sobol")
    assert sobol[-1][1] < sobol[0][1] and sum(x["default"] for x in out["flux"]["rows"]) == 1
    newton = out["newton"]
    rows = newton if isinstance(newton, list) else newton["rows"]
    # The robust solve converges to the float64 quartic's intersection with enough iterations.
    robust64 = [x for x in rows if x["method"].startswith("robust") and x["dtype"] == "float64"]
    assert robust64 and min(x["median_error_mm"] for x in robust64) < 1e-9
    assert all(x["seconds"] > 0 for x in rows)
