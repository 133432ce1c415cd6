"""Calibrate on some presses, judge on the others: the fixed split of the shared real frames.

Leave-presses-out CV reuses presses whose circles and refinement shaped the calibration, and a
user picks the model by it; a separate set of presses does neither. On the shared GelSight
frames (30 presses) the split is fixed: presses 0-19 calibrate, 20-29 test
(:data:`TRAIN_PRESSES`, :data:`TEST_PRESSES`). Choices (model options, levers) are made by
the CV on the training presses; the test figures are reported afterwards, never tuned on.
:func:`split_evaluation` is what ``iristac bench calibration`` and the tests run.
"""

from __future__ import annotations

import time
from typing import Any

from pipeline.base.capture import Capture

__all__ = ["TRAIN_PRESSES", "TEST_PRESSES", "split_evaluation", "split_rows", "best_row"]

#: The fixed split of the shared real frames (``../shared/data/gelsight_ball_presses.npz``).
TRAIN_PRESSES = slice(0, 20)
TEST_PRESSES = slice(20, 30)


def split_evaluation(capture: Capture, ball_radius_mm: float, models="all", *, train=TRAIN_PRESSES,
                     test=TEST_PRESSES, test_circles=None, **calibrate_kwargs) -> dict[str, Any]:
    """Calibrate on the ``train`` presses and evaluate every model on the ``test`` presses.

    Parameters
    ----------
    capture : Capture
    ball_radius_mm : float
    models : as :func:`calibration.calibrate.calibrate`
    train, test : slice or index array
    test_circles : CircleFit, optional
        The test presses' circles (``find_circles`` of ``capture.select(test)``), to reuse.
    **calibrate_kwargs
        Passed to :func:`calibration.calibrate.calibrate` (``model_options``, ``markers`` ...).

    Returns
    -------
    dict
        ``calibration`` (the CalibrationResult), ``evaluation`` (:func:`evaluate_calibration`'s
        result), ``seconds`` (the calibration's wall time), ``rows`` (:func:`split_rows`).
    """
    from calibration.calibrate import calibrate
    from calibration.evaluate import evaluate_calibration

    t = time.perf_counter()
    res = calibrate(capture.select(train), ball_radius_mm, models=models, **calibrate_kwargs)
    seconds = time.perf_counter() - t
    ev = evaluate_calibration(res, capture.select(test), ball_radius_mm, circles=test_circles,
                              markers=calibrate_kwargs.get("markers"))
    return {"calibration": res, "evaluation": ev, "seconds": seconds, "rows": split_rows(res, ev)}


def split_rows(result, evaluation: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per model: CV (training presses) beside test (detected and label truth) and the ball fit."""
    rows = []
    labels = (evaluation["truth"].get("labels") or {}).get("models", {})
    for name, m in evaluation["models"].items():
        rep = result.reports.get(name, {})
        bf = evaluation["ball_fit"].get(name, {})
        rows.append({
            "model": name,
            "cv_mean_deg": m.get("cv_mean_deg"),
            "test_mean_deg": m["mean_deg"],
            "test_median_deg": m["median_deg"],
            "labels_mean_deg": labels.get(name, {}).get("mean_deg"),
            "ball_radius_error": bf.get("radius_error_median"),
            "ball_depth_error": bf.get("depth_error_median"),
            "tilt_gain": (rep.get("cv") or {}).get("tilt_gain"),
            "seconds": rep.get("seconds"),
            "note": m.get("note"),
        })
    return rows


def best_row(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The row of the model with the lowest CV error (the choice a user makes without a test capture)."""
    scored = [r for r in rows if r["cv_mean_deg"] is not None]
    return min(scored, key=lambda r: r["cv_mean_deg"]) if scored else {}

