"""Calibration that generalizes: the fixed split of the shared real frames (presses 0-19 calibrate, 20-29 test).

Choices were made by CV on presses 0-19 (``iristac bench calibration`` prints the levers); the
test presses only check the result. Also: ``iristac eval calibration`` end to end, and markers
printed on the real frames.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from helpers import run_cli

_REPO = Path(__file__).resolve().parents[2]
DATA = next((p for p in (_REPO.parent / "shared" / "data" / "gelsight_ball_presses.npz",
                         _REPO.parent.parent / "shared" / "data" / "gelsight_ball_presses.npz") if p.is_file()),
            _REPO.parent / "shared" / "data" / "gelsight_ball_presses.npz")
pytestmark = pytest.mark.skipif(not DATA.is_file(), reason=f"shared real frames not found at {DATA}")


@pytest.fixture(scope="module")
def capture():
    from calibration.importers import load_gelsight_npz

    return load_gelsight_npz(DATA)


@pytest.fixture(scope="module")
def split(capture):
    from calibration.split import split_evaluation

    return split_evaluation(capture, 2.0, ["near", "mlp"])


def test_best_model_meets_the_test_split_targets(split):
    from calibration.split import best_row

    rows = {r["model"]: r for r in split["rows"]}
    best = best_row(split["rows"])
    assert best["model"] == "mlp", rows
    # Issue 13's targets on presses the calibration never saw (detected-circle truth, ball fit).
    assert best["test_mean_deg"] <= 7.0, best
    assert best["ball_radius_error"] <= 0.03, best
    # Not met, and reported: the hand labels' own centre bias (docs/calibration.md) costs ~8 deg alone.
    assert best["labels_mean_deg"] > 9.0


def test_cv_and_test_agree_or_the_report_says_so(split):
    for r in split["rows"]:
        gap = r["test_mean_deg"] - r["cv_mean_deg"]
        assert (abs(gap) > 2.0) == (r["note"] is not None), r


def test_text_report_names_every_model_and_flags_gaps(split):
    from calibration.evaluate import format_report

    text = format_report(split["evaluation"])
    assert "10 of 10 test presses accepted" in text
    for r in split["rows"]:
        assert f"  {r['model']:6s} {r['test_mean_deg']:9.2f}" in text
        assert (f"note: {r['model']}:" in text) == (r["note"] is not None)


def test_label_truth_is_reported_separately_with_its_bias(split):
    ev = split["evaluation"]
    lab = ev["truth"]["labels"]
    dx, dy = lab["center_offset_px_median"]
    assert dx > 0.5 and dy < -0.5  # the labels' bias holds on the test presses too
    assert set(lab["models"]) == {"near", "mlp"}
    for name, m in ev["models"].items():
        assert lab["models"][name]["mean_deg"] > m["mean_deg"], name


def test_eval_calibration_cli(tmp_path, capture, split):
    from pipeline.base.capture import write_capture
    from calibration.split import TEST_PRESSES

    cal = split["calibration"].save(tmp_path / "cal.h5")
    test = write_capture(tmp_path / "test.h5", capture.select(TEST_PRESSES))
    r = run_cli("eval", "calibration", cal, test, "--ball-radius", "2.0", "--json", "--model", "near")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert set(out) == {"presses", "accepted", "models", "truth", "ball_fit"}
    assert {"mean_deg", "median_deg", "p90_deg", "invalid_fraction", "per_press"} <= set(out["models"]["near"])
    assert set(out["truth"]) == {"detected", "labels"} and out["presses"] == 10
    fit = out["ball_fit"]["near"]
    assert len(fit["per_press"]) == 10 and {"radius_mm", "depth_mm", "radius_error"} <= set(fit["per_press"][0])
    # The file reproduces the in-memory evaluation of the same model.
    assert out["models"]["near"]["mean_deg"] == pytest.approx(split["evaluation"]["models"]["near"]["mean_deg"],
                                                              abs=0.01)
    r = run_cli("eval", "calibration", cal, tmp_path / "missing.h5")
    assert r.returncode == 2 and "missing.h5" in r.stderr and "Traceback" not in r.stderr


def test_markers_on_the_real_frames_cost_less_than_a_degree(capture, split):
    """Dark dots printed on every frame (reference included) at fixed places: detected in the reference,
    filled in and left out; the test-press error stays within 1 deg of the marker-free error."""
    from pipeline.base.capture import Capture
    from calibration.markers import draw_markers
    from calibration.split import split_evaluation

    frames, mask = draw_markers(capture.frames, spacing_px=12.0, radius_px=1.5)
    reference, _ = draw_markers(capture.reference, spacing_px=12.0, radius_px=1.5)
    marked = Capture(frames=frames, reference=reference, drive=capture.drive, brightness=capture.brightness,
                     mm_per_px=capture.mm_per_px, labels=capture.labels, meta=capture.meta)
    res = split_evaluation(marked, 2.0, ["mlp"], markers="auto")
    found = res["calibration"].markers
    assert found[mask].mean() > 0.95 and found.sum() < 2.5 * mask.sum()
    clean = {r["model"]: r for r in split["rows"]}["mlp"]["test_mean_deg"]
    with_markers = res["rows"][0]["test_mean_deg"]
    assert abs(with_markers - clean) <= 1.0, (clean, with_markers)
