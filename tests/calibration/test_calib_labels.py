"""Calibrating on hand-labelled circles (``calibrate(..., circles="labels")``, ``--circles labels``).

Rendered presses whose labels are the exact circles they were rendered with: a calibration on
them is as good as the shading allows; labels moved off the contacts make it worse; a capture
without labels is one clear error and writes nothing.
"""

import numpy as np
import pytest

from helpers import run_cli


@pytest.fixture(scope="module")
def rendered():
    from calibration.synthetic import synthetic_sphere_capture

    cap, tr = synthetic_sphere_capture((80, 100), 6, mm_per_px=0.1, ball_radius_mm=1.5, num_leds=6, peak_dn=140,
                                       seed=3)
    return cap, tr


def _with_labels(cap, centers_xy, radii):
    from pipeline.base.capture import Capture

    return Capture(frames=cap.frames, reference=cap.reference, drive=cap.drive, brightness=cap.brightness,
                   mm_per_px=cap.mm_per_px, meta=dict(cap.meta),
                   labels={"center_xy": np.asarray(centers_xy, np.float32), "radius_px": np.asarray(radii, np.float32)})


def test_exact_labels_calibrate_as_well_as_the_shading_allows(rendered):
    from calibration.calibrate import calibrate

    cap, tr = rendered
    exact = tr.centers_rc[:, ::-1]  # (row, col) -> (x = column, y = row)
    res = calibrate(_with_labels(cap, exact, tr.radii_px), 1.5, models=["near"], folds=3, circles="labels")
    np.testing.assert_allclose([c.center_xy for c in res.circles], exact, atol=1e-5)
    assert res.meta["circle_settings"]["circles"] == "labels" and res.meta["refine"]["iterations"] == 0
    assert "hand labels" in res.summary()["circles_used"]
    exact_cv = res.summary()["models"]["near"]["cv_mean_angular_error_deg"]
    assert exact_cv < 1.0
    # The detector's circles are still compared with the labels (they sit on the rendered contacts).
    assert res.labels["center_error_px_median"] < 0.5
    # Every label moved by the same 2 px: the models learn a shifted convention and the CV, judged
    # against those same labels, cannot stay near the exact one (a flat gel pins the offset).
    shifted = calibrate(_with_labels(cap, exact + [2.0, -2.0], tr.radii_px), 1.5, models=["near"], folds=3,
                        circles="labels")
    assert shifted.summary()["models"]["near"]["cv_mean_angular_error_deg"] > exact_cv + 2.0
    assert shifted.labels["center_offset_px_median"] == pytest.approx([-2.0, 2.0], abs=0.5)


def test_label_radius_is_clamped_below_the_ball(rendered):
    from calibration.labels import capture_label_circles

    cap, tr = rendered
    ball_px = 1.5 / 0.1
    circles = capture_label_circles(_with_labels(cap, tr.centers_rc[:, ::-1], np.full(6, 1.2 * ball_px)), ball_px)
    assert all(c.radius_px == pytest.approx(1.2 * ball_px) for c in circles)
    assert all(c.contact_radius_px == pytest.approx(0.95 * ball_px) and "clamped" in c.reason for c in circles)
    bad = capture_label_circles(_with_labels(cap, np.full((6, 2), np.nan), np.full(6, 10.0)), ball_px)
    assert not any(c.accepted for c in bad) and "not usable" in bad[0].reason


def test_auto_means_detected_even_with_labels(rendered):
    from calibration.calibrate import find_circles

    cap, tr = rendered
    labelled = _with_labels(cap, tr.centers_rc[:, ::-1] + 3.0, tr.radii_px)
    auto = find_circles(labelled, 1.5)
    assert auto.source_of_circles == "detected"
    assert np.median(np.hypot(*(np.array([c.center_xy for c in auto.circles]) - tr.centers_rc[:, ::-1]).T)) < 0.5


def test_labels_asked_for_but_absent_is_one_clear_error(rendered, tmp_path):
    from calibration.calibrate import calibrate
    from calibration.detect import Circle
    from pipeline.base.capture import write_capture
    from pipeline.base.errors import UserError

    cap, tr = rendered
    with pytest.raises(UserError, match="no hand labels"):
        calibrate(cap, 1.5, models=["near"], circles="labels")
    with pytest.raises(UserError, match="must be one of auto, detected, labels"):
        calibrate(cap, 1.5, models=["near"], circles="hand")
    with pytest.raises(UserError, match="6 Circle records"):
        calibrate(cap, 1.5, models=["near"], circles=[Circle((10.0, 10.0), 5.0, 5.0, 1.0, True, "given")])
    src = write_capture(tmp_path / "cap.h5", cap)
    out = tmp_path / "cal.h5"
    r = run_cli("calibrate", src, "--ball-radius", "1.5", "--model", "near", "--circles", "labels", "--out", out)
    assert r.returncode == 2 and "cap.h5: no hand labels" in r.stderr and "--circles detected" in r.stderr
    assert "Traceback" not in r.stderr and not out.exists()


def test_cli_calibrates_on_labels(rendered, tmp_path):
    import json

    from pipeline.base.capture import write_capture

    cap, tr = rendered
    src = write_capture(tmp_path / "cap.h5", _with_labels(cap, tr.centers_rc[:, ::-1], tr.radii_px))
    r = run_cli("calibrate", src, "--ball-radius", "1.5", "--model", "near", "--folds", "3", "--circles", "labels",
                "--out", tmp_path / "cal.h5", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert "hand labels" in s["circles_used"] and s["models"]["near"]["cv_mean_angular_error_deg"] < 1.0
    text = run_cli("calibrate", src, "--ball-radius", "1.5", "--model", "near", "--folds", "3", "--out",
                   tmp_path / "cal2.h5")
    assert text.returncode == 0 and "circles: detected (edge detector)" in text.stdout


def test_cv_judged_on_its_own_samples_is_plain_cv(rendered):
    """``cross_validate(judge=samples)`` is the ordinary CV; another truth changes only the judging."""
    from calibration.calibrate import find_circles
    from calibration.models import NearFieldModel
    from calibration.validate import cross_validate

    cap, tr = rendered
    found = find_circles(cap, 1.5)
    plain = cross_validate(NearFieldModel, found.samples, found.reference, folds=3)
    same = cross_validate(NearFieldModel, found.samples, found.reference, folds=3, judge=found.samples)
    assert same["cv_mean_angular_error_deg"] == pytest.approx(plain["cv_mean_angular_error_deg"], rel=1e-12)
    moved = find_circles(_with_labels(cap, tr.centers_rc[:, ::-1] + [2.0, 0.0], tr.radii_px), 1.5, circles="labels")
    judged = cross_validate(NearFieldModel, found.samples, found.reference, folds=3, judge=moved.samples)
    assert judged["cv_mean_angular_error_deg"] > plain["cv_mean_angular_error_deg"] + 2.0
    assert judged["folds"] == plain["folds"]
