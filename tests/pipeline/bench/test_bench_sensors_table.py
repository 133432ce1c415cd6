"""The ``bench calibration --sensors`` table prints what each row measured, scale and scatter apart."""

from __future__ import annotations

import pytest

from pipeline.bench._calibration_sensors import format_sensors


def _row(**over):
    row = {"sensor": "DIGIT (test row)", "presses": [20, 10], "accepted": [20, 10], "best_model": "mlp",
           "cv_deg": 5.7, "test_deg": 4.9, "ball_radius_error": 0.032, "ball_median_radius_error": -0.002,
           "ball_spread": 0.044, "gate": True, "seconds": 12.0, "ball_presses": [9, 10],
           "models": {"mlp": {"cv_deg": 5.7, "test_deg": 4.9, "ball_radius_error": 0.032, "usable": True,
                              "problems": []}}}
    row.update(over)
    return row


def test_sensor_rows_show_the_ball_scale_beside_its_scatter():
    lines = format_sensors({"sensors": [_row(), _row(sensor="no ball", ball_radius_error=None,
                                                     ball_median_radius_error=None, ball_spread=None)]})
    assert "scatter = how much single presses scatter" in lines[0]
    header = lines[1]
    assert header.index("ball") < header.index("r med") < header.index("scatter") < header.index("gate")
    row = next(line for line in lines if line.startswith("  DIGIT (test row)"))
    assert "3.2 %" in row and "-0.2 %" in row and "4.4 %" in row and "pass" in row
    empty = next(line for line in lines if line.startswith("  no ball"))
    assert "%" not in empty.split("pass")[0].split("4.90")[1]  # no figure where no sphere was fitted
    assert "9/10" in lines[-1]


def test_the_table_ends_with_what_each_target_asks_and_whether_it_is_met():
    """Real rows by their tag, plain virtual seeds on exact truth, each contact look against the
    same seeds without it (acceptance over every press, circle centres, the truth's gap)."""
    from pipeline.bench._calibration_sensors import sensor_targets

    def virtual(seed, look, truth, accepted=(18, 9), centres=(0.5, 0.6)):
        return _row(sensor=f"virtual seed {seed}", seed=seed, look=look, test_deg_truth=truth,
                    accepted=list(accepted), centre_error_px=list(centres))

    rows = [_row(sensor="GelSight (shared)", target="GelSight", test_deg=2.19, ball_radius_error=0.005),
            _row(target="DIGIT", test_deg=1.95, ball_radius_error=0.035), _row(sensor="DIGIT copy", target=None),
            virtual(0, None, 1.75), virtual(1, None, 2.27),
            virtual(0, "soft_shading", 3.57, (15, 8)), virtual(1, "soft_shading", 2.40, (18, 9), (1.4, 2.5)),
            virtual(0, "marker_motion", 2.36, (18, 9)), virtual(1, "marker_motion", 2.29, (18, 9))]
    lines = sensor_targets(rows)
    assert lines[0] == "target GelSight: test <= 3.5 deg and ball <= 3 %: met (2.19 deg, 0.5 %)"
    assert lines[1] == "target DIGIT: test <= 3.5 deg and ball <= 3 %: NOT met (1.95 deg, 3.5 %)"
    assert lines[2] == "target virtual sensors: truth <= 2.0 deg on every seed: NOT met (seed 0 1.75, seed 1 2.27)"
    soft = [line for line in lines if line.startswith("target soft_shading")]
    assert soft == ["target soft_shading: >= 90 % of presses accepted: NOT met (50/60; without the look 54)",
                    "target soft_shading: circle centres within 2 px: NOT met (row medians 0.50-2.50 px)",
                    "target soft_shading: truth within 1 deg of the same seed without it: NOT met (seed 0 +1.82, "
                    "seed 1 +0.13)"]
    moved = [line for line in lines if line.startswith("target marker_motion")]
    assert [line.split(": ")[2].split(" (")[0] for line in moved] == ["met", "met", "met"]
    assert len(lines) == 9
    assert lines[-1] in format_sensors({"sensors": rows})[-1]


def test_rows_are_reported_as_they_land_and_two_captures_give_the_split(tmp_path):
    """The quarter-hour bench says what it finished (the hook hears each row as it is returned), and
    its two-folder row equals the split row on the same presses."""
    from pipeline.bench._calibration_sensors import _virtual_rows

    heard = []
    rows = _virtual_rows([1], ["near"], tmp_path, heard.append)
    assert len(rows) == 1 and heard == rows
    assert heard[0]["sensor"].startswith("virtual seed 1 (120x160") and heard[0]["seconds"] > 0
    assert heard[0]["accepted"][1] >= 8 and heard[0]["test_deg"] < 10  # a real calibration, judged
    # The two-folder row (calibrate on one capture, evaluate on another) on the same presses as
    # the split gives the split's figures.
    from calibration.split import TEST_PRESSES, TRAIN_PRESSES
    from pipeline.base.capture import read_capture
    from pipeline.bench._calibration_sensors import _split_row

    cap = read_capture(tmp_path / "virtual_1.h5")
    two = _split_row("two", cap.select(TRAIN_PRESSES), float(cap.meta["ball_radius_mm"]), ["near"],
                     test_capture=cap.select(TEST_PRESSES))
    assert two["presses"] == [20, 10] and two["accepted"] == heard[0]["accepted"]
    for key in ("cv_deg", "test_deg", "ball_radius_error", "ball_spread"):
        assert two[key] == pytest.approx(heard[0][key], rel=1e-9), key
