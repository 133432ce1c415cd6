"""A new unit from a few presses (calibration.prior) and units of one virtual design (sim.virtual_sensor.sibling_unit)."""

import numpy as np
import pytest

from calibration.calibrate import calibrate
from calibration.gate import CalibrationRefused
from calibration.prior import MIN_NEW_PRESSES, adapt_mlp, calibrate_with_prior, load_prior
from calibration.stored import load_calibration
from pipeline.base.errors import UserError
from pipeline.results.evaluate import angular_error_deg
from sim.virtual_sensor import UNIT_VARIATION, random_sensor, render_sensor, sibling_unit

SHAPE = (60, 80)
FAST = {"steps": 80, "finetune_steps": 30}
STRONG = {"led_gain": 0.35, "white_tint": 0.3, "led_crosstalk": 0.15}


def _design():
    s = random_sensor(5, shape=SHAPE, num_presses=1, effects=["read_noise"], radius_range=(0.5, 0.9))
    return s.replace(mm_per_px=s.ball_radius_mm / 22.0)  # a 22 px ball: contacts of 11-20 px


@pytest.fixture(scope="module")
def units(tmp_path_factory):
    """A prior (unit A, 10 presses, a small MLP) and unit B's 5 presses, on disk and in memory."""
    d = tmp_path_factory.mktemp("prior")
    design = _design()
    a = render_sensor(sibling_unit(design, 1, num_presses=10)).capture
    res = calibrate(a, None, models="mlp", folds=2, tilt_correction=False,
                    model_options={"mlp": {"epochs": 150, "max_samples": 1500}})
    res.save(d / "a.h5", force=True)
    # unit B's LEDs differ more than most units' do: what the adaptation must undo is plain
    b = render_sensor(sibling_unit(design, 2, num_presses=5, variation=STRONG)).capture
    from pipeline.base.capture import write_capture

    write_capture(d / "b.h5", b)
    return {"dir": d, "prior": d / "a.h5", "b": b, "b_path": d / "b.h5", "design": design}


def test_sibling_units_keep_the_design_and_redraw_the_unit():
    design = _design()
    a, b = sibling_unit(design, 1), sibling_unit(design, 2)
    for u in (a, b):
        assert (u.shape, u.mm_per_px, u.ball_radius_mm, u.effects, u.ambient) == \
            (design.shape, design.mm_per_px, design.ball_radius_mm, design.effects, design.ambient)
    assert not np.allclose(a.led_rgb, b.led_rgb) and a.light_azimuths_deg != b.light_azimuths_deg
    assert a.to_dict() == sibling_unit(design, 1).to_dict()
    with pytest.raises(ValueError, match="unknown variation"):
        sibling_unit(design, 1, variation={"fog": 1.0})
    # With no variation the unit's LEDs are the design's: led_rgb's identity is the design's drive.
    same = sibling_unit(design, 3, variation={k: 0.0 for k in UNIT_VARIATION}, num_presses=1)
    assert np.array_equal(render_sensor(same).capture.reference,
                          render_sensor(same.replace(led_rgb=None)).capture.reference)
    # ... and a unit's own LEDs change the frames.
    assert not np.array_equal(render_sensor(a).capture.reference,
                              render_sensor(a.replace(led_rgb=None)).capture.reference)


def test_adapted_prior_beats_the_prior_on_the_new_unit_and_is_a_normal_calibration(units, tmp_path):
    res = calibrate_with_prior(units["b_path"], units["prior"], **FAST)
    cv = res.reports["mlp"]["cv"]
    assert cv["method"] == "leave-one-press-out" and len(cv["folds"]) == res.summary()["accepted"] >= MIN_NEW_PRESSES
    assert all(len(f["test_presses"]) == 1 for f in cv["folds"])
    # The truth-free judge: every held-out press reconstructed by the model adapted without it.
    ball = cv["ball_gain"]
    assert ball["attempted"] == len(cv["folds"]) and ball["presses"] >= 3, ball
    assert abs(ball["raw_radius_error"]) < 0.2 and res.summary()["ball_fit"]["model"] == "mlp", ball
    assert res.verdict.evidence["ball_radius_error"] == ball["raw_radius_error"]
    prior = load_prior(units["prior"])
    found_samples = _samples(res, units)
    con = found_samples.subset(found_samples.contact)
    before = angular_error_deg(prior.model.predict(con)[0], con.normals).mean()
    after = angular_error_deg(res.models["mlp"].predict(con)[0], con.normals).mean()
    assert after < before - 0.5, (before, after)
    out = res.save(tmp_path / "new.h5", force=True)
    models, meta = load_calibration(out)
    assert meta["prior"]["key"] == "models/mlp" and meta["prior"]["path"].endswith("a.h5")
    assert meta["prior"]["adaptation"]["finetune_steps"] == FAST["finetune_steps"]
    assert "transfers" in meta["prior"]["transfer"] and meta["chosen_model"] == "mlp"
    again = models["mlp"].predict(con)[0]  # written and read back: the same model
    assert np.allclose(again, res.models["mlp"].predict(con)[0], atol=1e-5)


def _samples(res, units):
    from calibration.calibrate import find_circles

    return find_circles(units["b"], None, refine_iterations=0, strict=False).samples


def test_adapt_without_steps_is_the_prior(units):
    prior = load_prior(units["prior"]).model
    s = _samples(None, units)
    same = adapt_mlp(prior, s, steps=0, finetune_steps=0)
    assert np.allclose(same.predict(s)[0], prior.predict(s)[0], atol=1e-6)


def test_bad_priors_and_too_few_presses_say_what_is_wrong(units, tmp_path):
    near = calibrate(units["b"], None, models="near", folds=2, tilt_correction=False)
    near.save(tmp_path / "near.h5", force=True)
    with pytest.raises(UserError, match=r"near\.h5: the prior holds no MLP \(no models/mlp"):
        calibrate_with_prior(units["b"], tmp_path / "near.h5")
    other = render_sensor(random_sensor(5, shape=(48, 64), num_presses=3, effects="none")).capture
    with pytest.raises(UserError, match=r"48 x 64 px .* prior .*a\.h5 was calibrated on 60 x 80 px .*models/mlp/reference"):
        calibrate_with_prior(other, units["prior"], **FAST)
    with pytest.raises(CalibrationRefused, match=r"needs at least 3 accepted presses"):
        calibrate_with_prior(units["b"].select(slice(0, 2)), units["prior"], **FAST)


def test_cli_calibrate_with_prior(units, tmp_path, capsys):
    from pipeline.base.capture import write_capture
    from pipeline.cli import main

    three, out = tmp_path / "three.h5", tmp_path / "cli.h5"
    write_capture(three, units["b"].select(slice(0, 3)))
    code = main(["calibrate", str(three), "--prior", str(units["prior"]), "--out", str(out), "--force",
                 "--adapt-steps", "40", "10"])
    text = capsys.readouterr().out
    assert code == 0 and "transfer:" in text and "leave-one-press-out" in text and out.is_file()
    meta = load_calibration(out)[1]
    assert meta["prior"]["adaptation"]["steps"] == 40 and meta["prior"]["adaptation"]["finetune_steps"] == 10
    assert main(["calibrate", str(three), "--prior", str(units["prior"]), "--model", "near", "--out", str(out)]) != 0
    assert "--prior adapts the prior's MLP" in capsys.readouterr().err


def test_prior_benchmark_table_says_whether_the_target_holds():
    from pipeline.bench._calibration_prior import format_prior

    row = {"seed": 0, "shape": [120, 160], "prior_cv_deg": 2.9, "own20_test_deg": 2.5, "prior5_test_deg": 3.9,
           "gap_deg": 1.4, "prior5_loo_deg": 4.5, "prior_as_is_test_deg": 5.6, "own5_test_deg": None,
           "prior5_gate": False, "prior5_seconds": 10.0, "own20_seconds": 20.0, "seconds": 40.0}
    lines = format_prior({"prior": [row], "target": {"what": "within 1 deg", "met": False}, "seconds": 40.0})
    assert lines[2].split()[:6] == ["0", "120x160", "2.90", "2.50", "3.90", "+1.40"] and "fail" in lines[2]
    assert lines[3] == "target: within 1 deg: NOT met" and lines[4].startswith("time: 40 s")
