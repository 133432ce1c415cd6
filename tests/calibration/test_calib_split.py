"""Calibration that generalizes: the fixed split of the shared real frames (presses 0-19 calibrate, 20-29 test).

Choices were made by CV on presses 0-19 (``iristac bench calibration`` prints the levers); the
test presses only check the result. Calibrated on the detected circles (the default) and on
the hand labels (``circles="labels"``), each judged against both truths. Also: ``iristac eval
calibration`` end to end, and markers printed on the real frames.
"""

import json
import re
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
def four(capture):
    from calibration.split import four_way

    return four_way(capture, 2.0, ["near", "mlp"])


@pytest.fixture(scope="module")
def split(four):
    return four["settings"]["detected"]


def test_best_model_meets_the_test_split_targets(four):
    from calibration.split import split_targets

    assert four["best"] == {"detected": "mlp", "labels": "mlp"}, four["rows"]
    targets = {t["target"]: t for t in split_targets(four)}
    # The fixed-split targets on presses the calibration never saw. Detected truth and ball fit: met
    # by the default (calibrated on detected circles).
    assert targets["test_detected"]["default"]["value"] <= 7.0, targets["test_detected"]
    assert targets["ball_radius"]["default"]["value"] <= 0.03, targets["ball_radius"]
    # Against hand labels: met when calibrated on the labels (the labeller's convention is
    # learnt), and the report says in which setting.
    lab = targets["test_labels"]
    assert lab["met"] and "labels" in lab["met_in"] and lab["per_setting"]["labels"]["value"] <= 9.0, lab
    assert targets["cv_gap"]["met"], targets["cv_gap"]


def test_cv_and_test_agree_or_the_report_says_so(four):
    for setting, run in four["settings"].items():
        for r in run["rows"]:
            # The gap is taken on the truth the CV was judged against (labels for a calibration on labels).
            test = r["labels_mean_deg"] if setting == "labels" else r["test_mean_deg"]
            assert r["cv_truth"] == setting and r["cv_gap_deg"] == pytest.approx(test - r["cv_mean_deg"])
            assert (abs(r["cv_gap_deg"]) > 2.0) == (r["note"] is not None), r


def test_calibrating_on_labels_learns_the_labels_convention(four, capture):
    """A calibration on hand labels scores better against labels, one on detected circles against
    the detector's circles: each truth has its own convention (about 2 px apart here)."""
    from calibration.split import TRAIN_PRESSES

    for r in four["rows"]:
        assert r["labels"]["labels_mean_deg"] < r["detected"]["labels_mean_deg"], r["model"]
    # The MLP learns either convention; the near-field model's own structure pins its centres
    # (its errors against the detector are close either way).
    mlp = next(r for r in four["rows"] if r["model"] == "mlp")
    assert mlp["detected"]["test_mean_deg"] < mlp["labels"]["test_mean_deg"]
    cal = four["settings"]["labels"]["calibration"]
    labels = np.asarray(capture.labels["center_xy"][TRAIN_PRESSES], float)
    np.testing.assert_allclose([c.center_xy for c in cal.circles], labels, atol=1e-4)
    assert max(c.contact_radius_px for c in cal.circles) <= 0.95 * 2.0 / 0.1245 + 1e-6
    assert cal.summary()["circles_used"].startswith("hand labels")


def test_detected_truth_is_the_same_whatever_the_calibration(capture, split):
    """No light model votes for the test truth, and the calibration's own settings do not change it."""
    from calibration.calibrate import calibrate
    from calibration.evaluate import evaluate_calibration
    from calibration.split import TEST_PRESSES, TRAIN_PRESSES

    refined = calibrate(capture.select(TRAIN_PRESSES), 2.0, models=["near"], refine_model="near",
                        shrink_px=3.0)
    assert refined.meta["circle_settings"]["refine_iterations"] == 2
    ev = evaluate_calibration(refined, capture.select(TEST_PRESSES), 2.0)
    base = split["evaluation"]["truth"]["detected"]
    assert ev["truth"]["detected"]["circles"] == base["circles"]
    assert all(c["shift_xy"] == [0.0, 0.0] for c in base["circles"])
    assert "edge detector alone" in base["method"] and "2 px margin" in base["method"]


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
    assert dx > 0.5 and dy < -0.5  # the labels' offset from the detector holds on the test presses too
    assert set(lab["models"]) == {"near", "mlp"}
    for name, m in ev["models"].items():
        assert lab["models"][name]["mean_deg"] > m["mean_deg"], name


def test_eval_calibration_cli(tmp_path, capture, split):
    from calibration.split import TEST_PRESSES
    from pipeline.base.capture import write_capture

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
    # The scale (signed median) and the scatter of single presses, beside the median |error|.
    signed = np.array([p["radius_error"] for p in fit["per_press"] if p["radius_error"] is not None])
    assert fit["fitted"] == signed.size >= 3
    assert fit["radius_error_signed_median"] == pytest.approx(np.median(signed))
    assert fit["radius_error_median"] == pytest.approx(np.median(np.abs(signed)))
    assert fit["radius_error_spread"] == pytest.approx(1.4826 * np.median(np.abs(signed - np.median(signed))))
    assert fit["radius_mm_median"] == pytest.approx(2.0 * (1 + fit["radius_error_signed_median"]), rel=1e-9)
    lo, hi = fit["radius_error_median_range"]  # where the median |error| falls on other draws of the presses
    assert np.abs(signed).min() <= lo <= fit["radius_error_median"] <= hi <= np.abs(signed).max() and lo < hi
    # The file reproduces the in-memory evaluation of the same model, on presses that lost the
    # drift the calibration's presses lost (recorded in the file).
    assert out["models"]["near"]["mean_deg"] == pytest.approx(split["evaluation"]["models"]["near"]["mean_deg"],
                                                              abs=0.01)
    assert out["truth"]["detected"]["drift"] == split["evaluation"]["truth"]["detected"]["drift"] == "gain_offset"
    r = run_cli("eval", "calibration", cal, test, "--ball-radius", "2.0", "--model", "near", "--drift", "none")
    assert r.returncode == 0 and "10 of 10 test presses accepted (drift removed from each: none)" in r.stdout, r.stderr
    assert re.search(r"ball fit: near: \d+ of 10 presses fitted; their median radius [\d.]+ mm, [+-][\d.]+ % off the "
                     r"ball; single presses scatter by [\d.]+ % \(1.48 MAD\); the median \|error\| [\d.]+ % would be [\d.]+-[\d.]+ % on "
                     r"another draw", r.stdout), r.stdout
    r = run_cli("eval", "calibration", cal, tmp_path / "missing.h5")
    assert r.returncode == 2 and "missing.h5" in r.stderr and "Traceback" not in r.stderr


def test_markers_on_the_real_frames_cost_less_than_a_degree(capture, split):
    """Dark dots printed on every frame (reference included) at fixed places: detected in the reference,
    filled in and left out; the test-press error stays within 1 deg of the marker-free error. The
    near-field model, whose split takes half the MLP's time: the markers are handled before any
    model sees a pixel (the MLP: 4.64 -> 4.56 deg with them; near 5.82 -> 5.84)."""
    from calibration.markers import draw_markers
    from calibration.split import split_evaluation
    from pipeline.base.capture import Capture

    frames, mask = draw_markers(capture.frames, spacing_px=12.0, radius_px=1.5)
    reference, _ = draw_markers(capture.reference, spacing_px=12.0, radius_px=1.5)
    marked = Capture(frames=frames, reference=reference, drive=capture.drive, brightness=capture.brightness,
                     mm_per_px=capture.mm_per_px, labels=capture.labels, meta=capture.meta)
    res = split_evaluation(marked, 2.0, ["near"], markers="auto")
    found = res["calibration"].markers
    assert found[mask].mean() > 0.95 and found.sum() < 2.5 * mask.sum()
    clean = {r["model"]: r for r in split["rows"]}["near"]["test_mean_deg"]
    with_markers = res["rows"][0]["test_mean_deg"]
    assert abs(with_markers - clean) <= 1.0, (clean, with_markers)


def test_drifted_presses_calibrate_as_well_as_the_originals(capture, split):
    """Every press (calibration and test) drifted against the untouched reference, per press and channel:
    gain up to +-15 %, offset up to +-30 DN. Drift removal leaves the accepted presses and the error on
    presses the calibration never saw within 1 deg of the undrifted run (the near-field model: cheap;
    the MLP's figures are in iristac bench calibration --sensors)."""
    from calibration.split import split_evaluation
    from pipeline.normals.drift import drifted_capture

    drifted = drifted_capture(capture, seed=0)
    assert np.abs(drifted.frames.astype(float) - capture.frames).mean() > 10
    res = split_evaluation(drifted, 2.0, ["near"])
    clean = {r["model"]: r for r in split["rows"]}["near"]
    assert res["calibration"].summary()["accepted"] == split["calibration"].summary()["accepted"]
    assert res["evaluation"]["accepted"] == split["evaluation"]["accepted"]
    assert abs(res["rows"][0]["test_mean_deg"] - clean["test_mean_deg"]) <= 1.0, (res["rows"][0], clean)
