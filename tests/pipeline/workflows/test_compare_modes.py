"""compare-modes and the demo, end to end through the CLI on a small virtual sensor."""

import json

import pytest

from cdp_chromium import CHART_CHECK_JS, Chromium, find_chromium, serve
from helpers import run_cli
from pipeline.base.errors import UserError
from pipeline.base.store import StageStore, read_record, write_record
from pipeline.workflows.compare_modes import compare_captures, render_mode_captures


@pytest.fixture(scope="module")
def small_sensor(tmp_path_factory):
    from sim.synthesize import save_illumination, synthesize

    d = tmp_path_factory.mktemp("sensor")
    model = synthesize("default", (40, 52), 0.45, rays=150_000, sampler="sobol")
    return model, save_illumination(model, d / "illumination.h5"), d


def test_compare_modes_cli_reports_every_mode_and_the_near_field_wins(small_sensor, tmp_path):
    _, ill, _ = small_sensor
    r = run_cli("compare-modes", "--out", tmp_path / "cm", "--illumination", ill, "--modes", "point", "trichromatic",
                "--json")
    assert r.returncode == 0, r.stderr
    data = json.loads(r.stdout)
    runs = {(x["mode"], x["solver"]): x for x in data["comparison"]["runs"]}
    assert {m for m, _ in runs} == {"point", "trichromatic"}
    # The virtual sensor renders with exactly the light field the near-field solver uses:
    # it must be accurate, and far better than the far-field (centre light vector) solver.
    near, far = runs[("point", "nearfield")], runs[("point", "lstsq")]
    assert near["normal_mean_error_deg"] < 2.0 < far["normal_mean_error_deg"]
    assert near["valid_fraction"] > 0.95 and near["patterns"] == 24
    # A single-frame mode gets a lookup table, or the report says why it could not: on this
    # 40 x 52 sensor (contacts of 4 px) the table leaves most colours unanswered. Never for want
    # of presses: five rendered presses once lost every table to the gate's minimum of six.
    assert ("trichromatic", "lut") in runs or "trichromatic" in data["lut_skipped"]
    assert "presses accepted (at least" not in data["lut_skipped"].get("trichromatic", ""), data["lut_skipped"]
    assert data["comparison"]["best"]["mode"] in {"point", "trichromatic"}
    page = (tmp_path / "cm" / "report.html").read_text()
    assert "point/nearfield: error" in page and (tmp_path / "cm" / "report.json").is_file()


def test_user_captures_without_truth_are_refused_clearly(small_sensor, tmp_path):
    model, ill, _ = small_sensor
    caps, _ = render_mode_captures(StageStore(tmp_path / "cache"), model, "test-illumination", ["trichromatic"],
                                   "test-object", tmp_path)
    rec = read_record(caps["trichromatic"])
    for k in [k for k in rec.data if k.startswith("truth/")]:
        del rec.data[k]
    p = write_record(tmp_path / "no_truth.h5", rec)
    with pytest.raises(UserError, match="no_truth.h5: capture of mode 'trichromatic' has no truth/normals"):
        compare_captures({"trichromatic": p}, illumination=ill)
    r = run_cli("compare-modes", "--out", tmp_path / "x", "--captures", f"trichromatic={p}", "--illumination", ill)
    assert r.returncode == 2 and "has no truth/normals" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("compare-modes", "--out", tmp_path / "x", "--captures", "trichromatic")
    assert r.returncode == 2 and "expected MODE=PATH" in r.stderr


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo"
    r = run_cli("demo", "--quick", "--out", out, "--json", timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    return out, json.loads(r.stdout)


def test_demo_quick_runs_end_to_end(demo):
    out, data = demo
    assert set(data["stages"]) == {"synthesize", "calibrate", "capture", "reconstruct"}
    modes = {x["mode"] for x in data["comparison"]["runs"]}
    assert modes == {"point", "monochromatic", "trichromatic", "multicolour"}
    assert all(x["normal_mean_error_deg"] is not None for x in data["comparison"]["runs"])
    # the single-frame modes get their lookup tables (the quality gate judges a LUT's CV over the
    # pixels it answers: six small rendered presses leave half of them unanswered, yet it works)
    runs = {(x["mode"], x["solver"]) for x in data["comparison"]["runs"]}
    assert {("trichromatic", "lut"), ("multicolour", "lut")} <= runs, data["stages"]["calibrate"]["lut_skipped"]
    assert data["calibration"]["accepted"] == data["settings"]["presses"]
    assert json.loads((out / "report.json").read_text())["comparison"] == data["comparison"]
    assert (out / "report.html").read_text().count("<img") >= 4 * 3
    assert data["summary_figure"] == str(out / "summary.png") and (out / "summary.png").stat().st_size > 20_000


@pytest.mark.skipif(find_chromium() is None, reason="no chromium on PATH (Debian: apt-get install -y chromium)")
def test_demo_report_charts_render_in_chromium(demo):
    out, _ = demo
    with serve(out) as url, Chromium() as browser:
        page = browser.open(f"{url}/report.html", ready="document.body.dataset.rendered")
        charts = page.evaluate(CHART_CHECK_JS)
        assert {c["id"] for c in charts} == {"chart-modes-capture", "chart-modes-recon"}
        assert all(c["svg"] and c["points"] >= 4 and c["overlaps"] == 0 for c in charts), charts
        assert page.errors == []


def test_bench_modes_rings_the_pair_iristac_live_runs():
    """The modes benchmark marks what `iristac live` runs without options (its mode falls back
    to the live session's default when no profile names one): the pair must exist as a row."""
    from pipeline.bench.modes import live_defaults
    from pipeline.live import DEFAULT_MODE
    from pipeline.workflows.compare_modes import ModeRun, comparison_rows

    mode, solver = live_defaults()
    assert (mode, solver) == (DEFAULT_MODE, "lut")
    runs = [ModeRun(mode, s, 1, 0.1, "measured", 0.4, 1.0, 0.5, 0.06, 1.0) for s in (solver, "nearfield")]
    rows = comparison_rows(runs, default=(mode, solver))
    assert [r["default"] for r in rows] == [True, False]
