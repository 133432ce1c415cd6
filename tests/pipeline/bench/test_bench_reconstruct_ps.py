"""``iristac bench reconstruct --sections ps``: rows with error and time per solver, masked and
on the bounding box, the end-to-end row and the targets' verdicts (a small object: a smoke test;
the figures come from the full-size run, docs/reconstruction.md)."""

from __future__ import annotations

import json

from helpers import run_cli
from pipeline.bench.reconstruct_ps import format_ps


def test_ps_section_reports_every_solver_masked_and_boxed():
    r = run_cli("bench", "reconstruct", "--quick", "--sections", "ps", "--ps-radius", "12", "--json", timeout=600)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["sizes"] == [] and out["ps"]["lights"] == 24
    objs = out["ps"]["objects"]
    assert set(objs) == {"specular sphere", "bumpy (cast shadows)", "Lambertian sphere"}
    for o in objs.values():
        assert set(o["solvers"]) == {"lstsq", "robust", "cauchy", "trimmed"}
        for v in o["solvers"].values():
            assert v["seconds"] > 0 and v["bbox_seconds"] > 0 and v["cpu_seconds"] >= 0 and 0 <= v["mean_deg"] < 90
    spec = objs["specular sphere"]["solvers"]
    assert spec["robust"]["mean_deg"] < spec["lstsq"]["mean_deg"]
    knobs = {row["knob"] for row in out["rows"]}
    assert any(k.startswith("PS solver, specular sphere") for k in knobs)
    assert "reconstruct capture.h5 (specular sphere)" in knobs
    table = format_ps(out["ps"])
    assert "target robust error <= 1.0 deg on the specular sphere" in table and "this run is smaller" in table
    assert table.count(": met") + table.count(": NOT met") == 6
