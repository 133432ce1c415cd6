"""What keeps a calibration's figures honest: dark reference pixels, vignetting, non-round caps, useless models.

Cheap by design (small synthetic captures, fitted models on their samples); the figures per
sensor are in ``iristac bench calibration --sensors`` (docs/calibration.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.ballfit import MIN_ROUNDNESS, ball_fit
from calibration.calibrate import _best
from calibration.evaluate import evaluate_models, format_report
from calibration.gate import model_problems
from calibration.models import FarFieldModel, NearFieldModel
from calibration.synthetic import synthetic_sphere_capture
from calibration.truth import sphere_cap
from calibration.validate import cross_validate
from helpers import calibration_samples


@pytest.fixture(scope="module")
def far_capture():
    return synthetic_sphere_capture((60, 80), 6, far_field=True, peak_dn=140, seed=3)


def test_a_black_reference_pixel_does_not_spoil_the_far_field_lights(far_capture):
    """A reference pixel at 0 DN (a marker, a vignetted corner) made the far-field ratio ~1e7 there:
    lights ~1e6 times too long, every prediction invalid. It is left out of the fit and has no normal."""
    s, ref = calibration_samples(*far_capture)
    good = FarFieldModel()
    good.fit(s, ref)
    dark_ref = ref.copy()
    k = int(np.argmax(s.contact))
    r, c = s.rows[k], s.cols[k]
    dark_ref[:, r, c, :] = 0.0
    s.reference[k] = 0.0
    bad = FarFieldModel()
    bad.fit(s, dark_ref)
    np.testing.assert_allclose(bad.lights, good.lights, atol=0.01 * np.abs(good.lights).max())
    n, ok = bad.predict(s.subset(np.arange(len(s)) == k))
    assert not ok[0] and n[0].tolist() == [0.0, 0.0, 1.0]
    n, ok = bad.predict(s.subset(s.contact))
    assert ok.mean() > 0.99


def test_near_field_model_reads_vignetting_from_the_reference():
    """The same presses under an albedo x irradiance falling to 0.55 in the corners: the near model
    divided by the reference's flat field keeps its CV error; the uniform-albedo one doubles it."""
    h, w = 60, 80
    yy, xx = np.mgrid[:h, :w]
    vignetting = 1.0 - 0.45 * (((yy - h / 2) / (h / 2)) ** 2 + ((xx - w / 2) / (w / 2)) ** 2)
    cv = {}
    for name, albedo in (("uniform", 1.0), ("vignetted", np.clip(vignetting, 0.2, 1.0))):
        s, ref = calibration_samples(*synthetic_sphere_capture((h, w), 6, peak_dn=140, seed=4, albedo=albedo))
        for flat in (True, False):
            cv[name, flat] = cross_validate(lambda flat=flat: NearFieldModel(flat=flat), s, ref,
                                            folds=3)["cv_mean_angular_error_deg"]
    assert cv["vignetted", True] < cv["uniform", True] + 0.25, cv
    assert cv["vignetted", False] > 1.7 * cv["uniform", False], cv
    assert cv["vignetted", True] < 0.7 * cv["vignetted", False], cv


def test_flat_normalised_near_model_stores_its_flat_field(far_capture):
    """What reconstruct reads back (calibration.stored) predicts as the fitted model does."""
    from calibration.stored import StoredLightField

    s, ref = calibration_samples(*far_capture)
    m = NearFieldModel()
    m.fit(s, ref)
    arrays = m.to_arrays()
    assert arrays["flat_field"].shape == (ref.shape[0], ref.shape[3]) + s.shape
    stored = StoredLightField("near", m.light_field(s.shape), arrays["flat_field"])
    np.testing.assert_allclose(stored.predict(s)[0], m.predict(s)[0], atol=1e-5)
    with pytest.raises(ValueError, match="reference"):
        NearFieldModel().fit(s)


def _cap_normals(squeeze_x: float = 1.0):
    mm, ball = 0.05, 2.0
    cap = sphere_cap((96, 96), (48.0, 48.0), 25.0, ball, mm)
    g = cap.gradients.copy()
    g[..., 0] *= squeeze_x
    from pipeline.base.frames import gradients_to_normals

    return gradients_to_normals(g[..., 0], g[..., 1]), mm, ball


def test_ball_fit_needs_a_round_cap():
    """A ball leaves a round cap whatever a model's tilt scale: a sphere's cap fits the ball (roundness 1);
    a cap whose x-tilts were lost (as where only two lights on one line reach the gel) gets no radius."""
    n, mm, ball = _cap_normals()
    ok = ball_fit(n, mm, ball)
    assert ok["roundness"] == pytest.approx(1.0, abs=0.02) and abs(ok["radius_error"]) < 0.01
    n, mm, ball = _cap_normals(squeeze_x=0.3)
    flat_x = ball_fit(n, mm, ball)
    assert flat_x["roundness"] < MIN_ROUNDNESS and flat_x["radius_mm"] is None
    assert flat_x["reason"].startswith("not round")


def test_useless_models_say_so_and_are_not_chosen():
    good = {"cv": {"cv_mean_angular_error_deg": 6.0, "invalid_fraction": 0.0,
                   "ball_gain": {"raw_radius_error": 0.02, "presses": 10, "attempted": 10}}}
    off_ball = {"cv": {"cv_mean_angular_error_deg": 5.0, "invalid_fraction": 0.0,
                       "ball_gain": {"raw_radius_error": 1.5, "presses": 10, "attempted": 10}}}
    no_bump = {"cv": {"cv_mean_angular_error_deg": 5.5, "invalid_fraction": 0.0,
                      "ball_gain": {"raw_radius_error": None, "presses": 0, "attempted": 10,
                                    "note": "only 0 of 10 held-out presses reconstruct as a round cap"}}}
    for r in (good, off_ball, no_bump):
        r["problems"] = model_problems(r["cv"])
    assert good["problems"] == [] and "150% off the ball" in off_ball["problems"][0]
    assert "show no ball" in no_bump["problems"][0]
    assert _best({"mlp": good, "near": off_ball, "lut": no_bump}) == "mlp"
    assert _best({"near": off_ball}) == "near"  # none usable: the gate judges the best anyway


class _Blind:
    """A model whose every prediction is invalid (as the far-field model with a black reference was)."""

    tilt_gain, max_tilt = 1.0, None

    def predict(self, samples):
        n = np.zeros((len(samples), 3))
        n[:, 2] = 1.0
        return n, np.zeros(len(samples), bool)


def test_a_model_without_valid_predictions_prints_no_90_degrees(far_capture):
    s, _ = calibration_samples(*far_capture)
    stats = evaluate_models({"far": _Blind()}, s)["far"]
    assert stats["mean_deg"] is None and stats["invalid_fraction"] == 1.0
    stats.update(problems=["no valid prediction on the test presses"], usable=False)
    result = {"presses": 6, "accepted": 6, "models": {"far": stats}, "truth": {"detected": {}},
              "ball_fit": {"far": {"radius_error_median": None, "depth_error_median": None}}}
    text = format_report(result)
    assert "90.00" not in text and "UNUSABLE: far: no valid prediction" in text
