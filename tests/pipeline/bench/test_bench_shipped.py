"""``iristac bench calibration --shipped``'s table, from the figures stored in the shipped file
(the measurement itself, a minute or two on the DIGIT frames, is the benchmark's to run)."""

from __future__ import annotations

from pipeline.bench._calibration_shipped import ALTERATION, format_shipped
from pipeline.capture.shipped import shipped_calibration_path, shipped_info


def test_table_sets_the_other_unit_beside_the_unit_itself():
    from calibration.altered_unit import Alteration

    info = shipped_info("digit")
    path = shipped_calibration_path("digit")
    # The stored copy is the one the bench makes: rebuilding measures what the file says.
    assert info["altered"]["alteration"] == Alteration(**ALTERATION).describe()
    seeded = {**info["altered"], "case": "seed 7", "mean_deg": info["altered"]["mean_deg"] + 1.0}
    result = {"shipped": True, "calibration": str(path), "size_bytes": path.stat().st_size, "stored": info,
              "original": info["original"], "altered": info["altered"], "seeded": [seeded], "seconds": 60.0}
    lines = format_shipped(result)
    text = "\n".join(lines)
    o, a = info["original"]["mean_deg"], info["altered"]["mean_deg"]
    assert "built from 20 presses, MIT" in lines[0]
    row = next(line for line in lines if line.lstrip().startswith("another unit: altered copy"))
    assert f"{a:.2f}" in row and f"{100 * info['altered']['ball_radius_error']:.1f} %" in row
    assert f"another unit vs the unit itself: {a - o:+.2f} deg (target: within 3 deg)" in text
    assert "another unit (seed 7)" in text and f"{a + 1.0:.2f}" in text


def test_table_sets_calibrate_prior_beside_the_shipped_one_as_it_is():
    from pipeline.bench._calibration_shipped import PRIOR_PRESSES, PRIOR_TEST

    info = shipped_info("digit")
    path = shipped_calibration_path("digit")
    as_is = {**info["altered"], "mean_deg": 4.5}
    adapted = {**info["altered"], "mean_deg": 4.25, "calibrate_seconds": 30.0, "loo_deg": 6.5,
               "transfer": {"reason": "the new presses' leave-one-out error 6.50 deg is within 2 deg"}}
    result = {"shipped": True, "calibration": str(path), "size_bytes": path.stat().st_size, "stored": info,
              "original": info["original"], "altered": info["altered"], "seconds": 60.0,
              "prior": {"as_is": as_is, "adapted": adapted}}
    text = "\n".join(format_shipped(result))
    assert f"from {len(PRIOR_PRESSES)} of its presses" in text and f"{PRIOR_TEST[0]}-{PRIOR_TEST[-1]}" in text
    row = next(line for line in text.splitlines() if "calibrate --prior shipped" in line)
    assert "4.25" in row
    assert "leave one press out) 6.50 deg" in text
    assert "--prior" not in "\n".join(format_shipped({k: v for k, v in result.items() if k != "prior"}))
