"""Traced model from an illumination record, and the optional LED position/tilt corrections
on a synthetic truth whose LEDs sit off their nominal places."""

import json

import numpy as np
import pytest

from calibration.calibrate import calibrate
from calibration.detect import detect_contacts
from calibration.models import TracedModel
from calibration.models.led_geometry import geometry_basis, tilt_axes
from calibration.samples import collect_samples
from calibration.synthetic import ring_illumination, synthetic_sphere_capture
from helpers import run_cli
from pipeline.base.capture import write_capture
from sim.point_source import ring_geometry
from sim.synthesize import save_illumination

SHAPE, MM, GEL_Z, L = (60, 80), 0.1, 30.0, 6


@pytest.fixture(scope="module")
def displaced():
    """Presses rendered with LEDs moved by up to 1 mm and tilted by up to 3 degrees."""
    pos, ax = ring_geometry(L, 40.0)
    rng = np.random.default_rng(1)
    dpos = rng.uniform(-1, 1, (L, 3)) * [1.0, 1.0, 0.5]
    tilt = np.radians(rng.uniform(-3, 3, (L, 2)))
    truth = ring_illumination(SHAPE, MM, L, gel_z=GEL_Z, positions=pos + dpos, axes=tilt_axes(ax, tilt))
    cap, tr = synthetic_sphere_capture(SHAPE, 8, ball_radius_mm=1.5, illumination=truth, peak_dn=140, seed=3)
    return cap, tr, truth, ring_illumination(SHAPE, MM, L, gel_z=GEL_Z)


def test_geometry_corrections_recover_the_displaced_field(displaced):
    cap, tr, truth, nominal = displaced
    f, r = cap.linear()
    s = collect_samples(f, r, detect_contacts(f, r, 15.0), 1.5, MM, saturation=255)
    plain = TracedModel(nominal.V, cap.drive)
    rep0 = plain.fit(s, r)
    basis = geometry_basis(nominal.led_positions, None, SHAPE, MM, GEL_Z)
    corr = TracedModel(nominal.V, cap.drive, basis=basis)
    rep1 = corr.fit(s, r)
    # The corrected light field (gains x fields: what the solvers use) is much closer to the
    # true one than the nominal fields with their best gains. (Fields alone are not: a tilt and
    # a sideways shift, or a height change and a gain, light the small gel almost alike.)
    from sim.illumination_model import light_matrices

    true_lf = light_matrices(truth.V, cap.drive, gains=tr.gains * tr.exposure / np.pi)
    before = np.linalg.norm(plain.light_field(SHAPE) - true_lf)
    after = np.linalg.norm(corr.light_field(SHAPE) - true_lf)
    assert after < 0.5 * before, (after, before)
    # Residual down to the noise (1 DN read noise + 8-bit rounding), and a better fit of normals.
    assert rep1["residual_rms_dn"] < rep0["residual_rms_dn"] and rep1["residual_rms_dn"] < 1.15
    assert rep1["train_mean_angular_error_deg"] < rep0["train_mean_angular_error_deg"]
    # A gain trades against height and tilt (an LED's brightness), but not against its colour:
    # each LED's channel ratios are the truth's within 1 %.
    want = tr.gains * tr.exposure / np.pi
    ratio = corr.gains / want
    assert np.abs(ratio / ratio[:, :1] - 1).max() < 0.01
    assert np.shape(rep1["led_position_correction_mm"]) == (L, 3)


def test_no_basis_means_no_correction(displaced):
    cap, tr, truth, nominal = displaced
    f, r = cap.linear()
    s = collect_samples(f, r, detect_contacts(f, r, 15.0), 1.5, MM, saturation=255)
    m = TracedModel(nominal.V, cap.drive)
    m.fit(s, r)
    assert m.theta is None and m.V is m.V0 and "geometry_correction" not in m.to_arrays()


def test_cli_traced_with_illumination_file(displaced, tmp_path):
    cap, tr, truth, nominal = displaced
    write_capture(tmp_path / "cap.h5", cap)
    save_illumination(nominal, tmp_path / "ill.h5")
    args = ["calibrate", tmp_path / "cap.h5", "--ball-radius", "1.5", "--model", "traced", "--illumination",
            tmp_path / "ill.h5", "--out", tmp_path / "cal.h5", "--json", "--folds", "3"]
    r = run_cli(*args, "--correct-led-geometry")
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)["models"]["traced"]
    assert got["cv_mean_angular_error_deg"] < 1.5 and len(got["fit"]["led_tilt_correction_deg"]) == L
    from pipeline.base.store import read_record

    rec = read_record(tmp_path / "cal.h5", "calibration")
    assert rec.data["models/traced/geometry_correction"].shape == (L, 5)
    # A wrong-size illumination model and a missing file are one-line errors naming the problem.
    save_illumination(ring_illumination((30, 40), MM, L), tmp_path / "small.h5")
    bad = run_cli(*args[:7], tmp_path / "small.h5", *args[8:])
    assert bad.returncode == 2 and "(30, 40)" in bad.stderr and "Traceback" not in bad.stderr
    bad = run_cli(*args[:7], tmp_path / "none.h5", *args[8:])
    assert bad.returncode == 2 and "none.h5" in bad.stderr


def test_geometry_correction_needs_led_positions(displaced):
    cap, tr, truth, nominal = displaced
    from pipeline.base.errors import UserError

    with pytest.raises(UserError, match="IlluminationModel"):
        calibrate(cap, 1.5, models=["traced"], illumination=nominal.V, folds=2,
                  model_options={"traced": {"correct_geometry": True}}, refine_iterations=0)


def test_refinement_votes_with_the_traced_model_when_fields_are_given(displaced):
    from pipeline.base.errors import UserError

    cap, tr, truth, nominal = displaced
    with_fields = calibrate(cap, 1.5, models=["traced"], illumination=truth, folds=3)
    assert with_fields.meta["refine"]["model"] == "traced"
    # The traced model measures these presses well, so its votes keep the centres on the truth.
    assert with_fields.summary()["models"]["traced"]["cv_mean_angular_error_deg"] < 1.5
    # Without LED fields no model votes by default: a fitted model's votes are its family's own
    # convention (docs/calibration.md, "Which truth"); the detector's centres stay.
    without = calibrate(cap, 1.5, models=["near"], folds=3)
    assert without.meta["refine"]["model"] is None and without.meta["refine"]["iterations"] == 0
    assert all(c.shift_xy == (0.0, 0.0) for c in without.circles)
    asked = calibrate(cap, 1.5, models=["near"], folds=3, refine_model="near")
    assert asked.meta["refine"]["model"] == "near" and asked.meta["circle_settings"]["refine_iterations"] == 2
    with pytest.raises(UserError, match="refinement with the 'traced' model is impossible"):
        calibrate(cap, 1.5, models=["near"], folds=3, refine_model="traced")
    with pytest.raises(UserError, match="--refine-model must be one of"):
        calibrate(cap, 1.5, models=["near"], folds=3, refine_model="lut")


def test_summary_reports_no_number_when_no_prediction_is_valid(displaced):
    """CV scores an invalid prediction as 90 deg; with none valid the summary says so instead."""
    cap, tr, truth, nominal = displaced
    res = calibrate(cap, 1.5, models=["near"], folds=3, refine_iterations=0)
    res.reports["near"]["cv"].update(cv_mean_angular_error_deg=90.0, cv_median_angular_error_deg=90.0,
                                     invalid_fraction=1.0)
    got = res.summary()["models"]["near"]
    assert got["cv_mean_angular_error_deg"] is None and got["cv_median_angular_error_deg"] is None
    assert got["cv_invalid_fraction"] == 1.0 and "no valid predictions" in got["note"]


def test_cli_refine_model_without_fields_is_one_line_and_keeps_the_old_output(displaced, tmp_path):
    cap, tr, truth, nominal = displaced
    write_capture(tmp_path / "cap.h5", cap)
    out = tmp_path / "cal.h5"
    out.write_bytes(b"an earlier calibration")
    r = run_cli("calibrate", tmp_path / "cap.h5", "--ball-radius", "1.5", "--model", "near", "--refine-model",
                "traced", "--out", out)
    assert r.returncode == 2 and "refinement with the 'traced' model is impossible" in r.stderr
    assert "Traceback" not in r.stderr and out.read_bytes() == b"an earlier calibration"


@pytest.mark.parametrize("seed", range(6))
def test_tall_nnls_on_the_qr_factor_equals_scipy_nnls(seed):
    """The gain fit's NNLS on the triangular factor of [A | b] finds scipy's NNLS solution of the
    full tall problem and its residual norm: well and badly conditioned columns (scaled over six
    decades), active bounds, an exact fit, and a repeated column (a rank-deficient A)."""
    from scipy.optimize import nnls

    from calibration.models.traced import nnls_tall

    rng = np.random.default_rng(seed)
    m, n = int(rng.integers(60, 3000)), int(rng.integers(2, 25))
    A = rng.random((m, n)) * 10.0 ** rng.uniform(-3, 3, n)
    x_true = np.where(rng.random(n) < 0.3, 0.0, rng.random(n)) / np.abs(A).max(0)
    b = A @ x_true
    if seed % 2:
        b = b - 0.3 * A[:, 0] * x_true.max() + rng.normal(0, 1e-3 * np.abs(b).mean(), m)  # some bounds active
    if seed == 4:
        A[:, -1] = A[:, 0]
    x, r = nnls_tall(A, b)
    x0, r0 = nnls(A, b, maxiter=50 * n)
    assert x.shape == (n,) and x.min() >= 0
    assert r == pytest.approx(np.linalg.norm(A @ x - b), rel=1e-6, abs=1e-9 * np.linalg.norm(b))
    assert r <= r0 + 1e-9 * np.linalg.norm(b)  # as good a fit (a rank-deficient A has many minimisers)
    if seed != 4:
        np.testing.assert_allclose(A @ x, A @ x0, rtol=0, atol=1e-7 * np.abs(b).max())
    with pytest.raises(ValueError, match=r"got \(5, 2\) and \(4,\)"):
        nnls_tall(np.ones((5, 2)), np.ones(4))


@pytest.mark.parametrize("seed", range(4))
def test_nnls_on_the_gram_matrix_equals_nnls_on_the_rows(seed):
    """From A^T A, A^T b and b^T b alone: the rows' NNLS solution and residual norm, and no answer
    (None) where the Gram matrix is singular or too ill-conditioned to trust."""
    from calibration.models.traced import MAX_GRAM_CONDITION, nnls_on_gram, nnls_tall

    rng = np.random.default_rng(seed)
    m, n = int(rng.integers(50, 2000)), int(rng.integers(2, 25))
    A = rng.random((m, n))
    b = A @ np.where(rng.random(n) < 0.3, 0.0, rng.random(n)) - 0.2 * A[:, 0] + rng.normal(0, 0.01, m)
    x, r = nnls_on_gram(A.T @ A, A.T @ b, float(b @ b))
    x0, r0 = nnls_tall(A, b)
    np.testing.assert_allclose(x, x0, atol=1e-8 * max(1.0, np.abs(x0).max()))
    assert r == pytest.approx(r0, rel=1e-6, abs=1e-9)
    bad = A.copy()
    bad[:, -1] = bad[:, 0] * (1 + 1e-7)  # two columns alike to 1e-7: condition ~1e14 in the Gram matrix
    assert np.linalg.cond(bad.T @ bad) > MAX_GRAM_CONDITION
    assert nnls_on_gram(bad.T @ bad, bad.T @ b, float(b @ b)) is None
    with pytest.raises(ValueError, match=r"gram must be \(3, 3\) like atb, got \(2, 2\)"):
        nnls_on_gram(np.eye(2), np.ones(3), 1.0)


@pytest.mark.parametrize("mode", ["point", "monochromatic", "trichromatic"])
def test_traced_gains_from_the_gram_matrix_equal_the_gains_from_the_rows(mode, monkeypatch):
    """The traced model's per-LED gains built from the small Gram matrices equal those of the full
    (pixel x pattern) rows solved on their QR factor, the path every ill-conditioned drive takes."""
    import calibration.models.traced as traced
    from pipeline.base.modes import load_mode

    ill = ring_illumination(SHAPE, MM, 24, gel_z=GEL_Z)
    cap, _ = synthetic_sphere_capture(SHAPE, 8, ball_radius_mm=1.5, illumination=ill, peak_dn=140, seed=3,
                                      num_leds=24, drive=load_mode(mode).drive)
    f, r = cap.linear()
    s = collect_samples(f, r, detect_contacts(f, r, 15.0), 1.5, MM, saturation=255)
    fast = TracedModel(ill.V, cap.drive, cap.brightness)
    rep = fast.fit(s, r)
    monkeypatch.setattr(traced, "MAX_GRAM_CONDITION", 0.0)  # every Gram matrix refused: the rows' path
    rows = TracedModel(ill.V, cap.drive, cap.brightness)
    rep_rows = rows.fit(s, r)
    np.testing.assert_allclose(fast.gains, rows.gains, rtol=0, atol=1e-9 * np.abs(rows.gains).max())
    assert rep["residual_rms_dn"] == pytest.approx(rep_rows["residual_rms_dn"], rel=1e-6)
    assert rep["residual_rms_dn"] < 1.2  # read noise (1 DN) and 8-bit rounding: the fit is right too
