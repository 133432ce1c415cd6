"""The batched prediction API of every calibration model, the ball-fit check, and gel markers."""

import numpy as np
import pytest

from calibration.ballfit import ball_fit, fit_sphere
from calibration.truth import sphere_cap
from sim.geometry.shapes import cap_depth


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A small rendered capture (one RGB pattern: every model applies) calibrated with all models."""
    from calibration.calibrate import calibrate
    from calibration.synthetic import synthetic_sphere_capture

    # Three LEDs lit red, green and blue in one frame: a GelSight-like single RGB pattern.
    cap, truth = synthetic_sphere_capture((48, 64), 8, num_leds=3, drive=np.eye(3)[None], mm_per_px=0.1,
                                          ball_radius_mm=1.5, peak_dn=150, seed=3)
    res = calibrate(cap, 1.5, models=["far", "near", "lut", "mlp"], folds=4,
                    model_options={"mlp": {"epochs": 60, "max_samples": 1500}})
    path = res.save(tmp_path_factory.mktemp("cal") / "cal.h5")
    return cap, truth, res, path


def test_every_model_gives_finite_normals_mask_and_confidence(fitted):
    cap, _, res, _ = fitted
    frames, ref = cap.linear()
    frames = frames.copy()
    frames[0, 0, 5, 7, 1] = np.nan  # a broken observation
    for name, model in res.models.items():
        nm = model.normal_maps(frames[:3], ref)
        assert nm.normals.shape == (3, 48, 64, 3) and nm.normals.dtype == np.float32, name
        assert np.isfinite(nm.normals).all() and np.isfinite(nm.confidence).all(), name
        np.testing.assert_allclose(np.linalg.norm(nm.normals, axis=-1), 1.0, atol=1e-5, err_msg=name)
        assert not nm.mask[0, 5, 7] and nm.normals[0, 5, 7].tolist() == [0.0, 0.0, 1.0], name
        assert ((nm.confidence >= 0) & (nm.confidence <= 1)).all() and (nm.confidence[~nm.mask] == 0).all(), name
        assert nm.mask.mean() > 0.9 and nm.meta["model"] == name and nm.meta["confidence"], name


def test_stored_models_predict_like_the_fitted_ones(fitted):
    from calibration.stored import load_calibration

    cap, _, res, path = fitted
    frames, ref = cap.linear()
    loaded, meta = load_calibration(path)
    assert set(loaded) == set(res.models)
    for name, model in res.models.items():
        a, b = model.normal_maps(frames[:2], ref), loaded[name].normal_maps(frames[:2], ref)
        assert loaded[name].tilt_gain == pytest.approx(model.tilt_gain) and model.tilt_gain != 1.0, name
        np.testing.assert_allclose(a.normals, b.normals, atol=1e-4, err_msg=name)
        assert (a.mask == b.mask).mean() > 0.999, name


def test_tilt_gain_is_fitted_on_held_out_presses_and_helps_cv(fitted):
    _, _, res, _ = fitted
    for name, rep in res.reports.items():
        cv = rep["cv"]
        assert 0.8 < cv["tilt_gain"] < 1.3, name
        # The gain is the one that undoes the held-out shrinkage: the CV error does not get worse.
        assert cv["cv_mean_angular_error_deg"] <= cv["cv_uncorrected_mean_angular_error_deg"] + 0.05, name


def test_markers_are_filled_and_masked(fitted):
    from calibration.markers import draw_markers

    cap, _, res, _ = fitted
    frames, ref = cap.linear()
    marked, mask = draw_markers(frames[:2], spacing_px=9.0, radius_px=1.2)
    ref_m, _ = draw_markers(ref, spacing_px=9.0, radius_px=1.2)
    clean = res.models["near"].normal_maps(frames[:2], ref)
    nm = res.models["near"].normal_maps(marked, ref_m, markers=mask)
    assert not nm.mask[:, mask].any() and nm.meta["markers"] == int(mask.sum()) and (nm.filled == mask).all()
    # Filled-in markers stay close to the marker-free prediction (they are interpolated, not dark).
    err = np.degrees(np.arccos(np.clip(np.sum(nm.normals * clean.normals, -1), -1, 1)))
    assert np.median(err[:, mask]) < 3.0


def test_detect_markers_finds_drawn_dots_on_uneven_light():
    from calibration.markers import detect_markers, draw_markers

    yy, xx = np.mgrid[:60, :80]
    ref = np.stack([80 + 100 * xx / 80, 60 + 80 * yy / 60, 120 - 0.5 * xx], -1)  # strongly uneven lighting
    marked, truth = draw_markers(ref, spacing_px=12.0, radius_px=1.5, darkness=0.6)
    found = detect_markers(marked)
    assert found[truth].mean() > 0.95  # every dot covered
    assert found.sum() < 3 * truth.sum()  # and not much else
    assert not detect_markers(ref).any()  # no dots, none found


def test_sphere_fit_on_exact_cap_normals():
    cap = sphere_cap((120, 160), (61.3, 77.8), 14.0, 2.0, 0.1245)
    r = ball_fit(cap.normals, 0.1245, 2.0, true_depth_mm=float(cap_depth(2.0, 14.0 * 0.1245)))
    assert abs(r["radius_error"]) < 0.005 and abs(r["depth_error"]) < 0.02 and r["pixels"] > 100


def test_sphere_fit_refuses_a_contact_cut_by_the_border():
    """Exact normals of a cap cut by the image edge integrate to no sphere (the integrator holds
    the edge flat): given its circle the fit says so instead of reporting a wrong radius; a cap
    whose rim barely leaves the image (as DIGIT test presses 28 and 29 do) still fits the ball."""
    from calibration.ballfit import MIN_RIM_INSIDE
    from calibration.detect import rim_inside

    cut = sphere_cap((120, 160), (8.0, 60.0), 14.0, 2.0, 0.1245)  # centre (row, col); circles are (x, y)
    assert ball_fit(cut.normals, 0.1245, 2.0)["radius_error"] > 0.1  # what the fit alone reports
    r = ball_fit(cut.normals, 0.1245, 2.0, contact=(60.0, 8.0, 14.0))
    assert r["radius_mm"] is None and "border" in r["reason"] and "69% of its rim" in r["reason"], r["reason"]
    grazing = sphere_cap((120, 160), (13.0, 60.0), 14.0, 2.0, 0.1245)
    assert MIN_RIM_INSIDE < rim_inside((120, 160), (60.0, 13.0), 14.0) < 0.9
    assert abs(ball_fit(grazing.normals, 0.1245, 2.0, contact=(60.0, 13.0, 14.0))["radius_error"]) < 0.005
    with pytest.raises(ValueError, match=r"\(120, 160\)"):
        ball_fit(grazing.normals[..., 0], 0.1245, 2.0)


def test_sphere_fit_sees_too_flat_normals():
    """Normals 10 % too flat (the shrinkage the tilt gain undoes) read as a larger ball."""
    from calibration.models.base import scale_tilt

    cap = sphere_cap((120, 160), (60.0, 80.0), 13.0, 2.0, 0.1245)
    flat, _ = scale_tilt(cap.normals, 0.9)
    r = ball_fit(flat, 0.1245, 2.0)
    assert 0.07 < r["radius_error"] < 0.16


def test_fit_sphere_needs_points():
    with pytest.raises(ValueError, match="at least 4"):
        fit_sphere(np.zeros(3), np.zeros(3), np.zeros(3))
    flat = np.zeros((20, 20, 3))
    flat[..., 2] = 1.0
    assert ball_fit(flat, 0.1, 1.0)["radius_mm"] is None
