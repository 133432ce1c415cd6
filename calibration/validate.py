"""Leave-presses-out cross-validation of a calibration model.

Presses are split into ``folds`` groups (seeded permutation); for each fold the model is
fitted on every sample whose press is *not* in the fold (reference pixels, ``press = -1``,
always train) and evaluated on the fold's contact pixels. Invalid predictions count as
90 degrees so that a model cannot look good by refusing to answer.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from calibration.models.base import CalibrationModel
from calibration.samples import Samples
from pipeline.results.evaluate import angular_error_deg

__all__ = ["cross_validate", "cv_report", "fold_assignment"]

INVALID_ERROR_DEG = 90.0


def fold_assignment(presses: np.ndarray, folds: int, seed: int = 0) -> dict[int, int]:
    """Map each press index to a fold in ``range(min(folds, len(presses)))``.

    Examples
    --------
    >>> sorted(fold_assignment(np.array([0, 1, 2, 3]), 2).values())
    [0, 0, 1, 1]
    """
    presses = np.unique(np.asarray(presses))
    k = max(1, min(int(folds), len(presses)))
    perm = np.random.default_rng(seed).permutation(len(presses))
    return {int(presses[i]): int(j % k) for j, i in enumerate(perm)}


def cross_validate(make_model: Callable[[], CalibrationModel], samples: Samples, reference: np.ndarray,
                   folds: int = 5, seed: int = 0, return_predictions: bool = False, judge: Samples | None = None,
                   fold_hook: Callable[[CalibrationModel, list[int]], None] | None = None):
    """Cross-validated angular error of the model built by ``make_model``.

    Parameters
    ----------
    make_model : callable
        Returns a fresh, unfitted model.
    samples : Samples
    reference : ndarray, shape (P, H, W, C)
    folds : int
        Number of press groups (leave-one-press-out when ``folds >= presses``).
    seed : int
    return_predictions : bool
        Also return the out-of-fold predictions.
    judge : Samples, optional
        Other truth for the same presses (e.g. their hand-labelled circles, or the detector's
        unrefined ones): each fold's model, fitted on ``samples``, is judged on ``judge``'s
        contact pixels of its held-out presses. Training choices that change the circles
        (refinement, labels) are comparable only against one fixed truth.
    fold_hook : callable, optional
        Called as ``fold_hook(model, held_out_presses)`` with each fold's fitted model (e.g. to
        reconstruct the held-out presses: :func:`calibration.calibrate.calibrate`'s ball fit).

    Returns
    -------
    dict
        ``cv_mean_angular_error_deg``, ``cv_median_angular_error_deg``, ``per_press``
        (press -> mean, median, samples), ``folds`` (list of ``{"train_presses", "test_presses"}``),
        ``invalid_fraction``.
    predictions : (normals (N, 3), valid (N,), evaluated (N,)), only with ``return_predictions``
        Each held-out contact sample's prediction by the model that did not see its press
        (``evaluated`` marks them; elsewhere ``(0, 0, 1)`` and False); of ``judge``'s samples when given.
    """
    from pipeline.base.threads import limit_threads

    with limit_threads(blas=1):  # why: see calibration.calibrate.calibrate
        report, preds = _cross_validate(make_model, samples, reference, folds, seed, judge, fold_hook)
    return (report, preds) if return_predictions else report


def cv_report(errors: np.ndarray, samples: Samples, fold_log: list) -> dict[str, Any]:
    """The CV statistics of per-sample errors ``(N,)`` (NaN where not evaluated; invalid = 90)."""
    evaluated = np.isfinite(errors)
    per_press = {}
    for p in np.unique(samples.press[evaluated]):
        e = errors[(samples.press == p) & evaluated]
        per_press[int(p)] = {"mean_deg": float(e.mean()), "median_deg": float(np.median(e)), "samples": int(e.size)}
    e = errors[evaluated]
    answered = e[e < INVALID_ERROR_DEG]
    return {"cv_mean_angular_error_deg": float(e.mean()), "cv_median_angular_error_deg": float(np.median(e)),
            # over the pixels the model answered (a lookup table leaves colours it never saw unanswered)
            "cv_answered_mean_angular_error_deg": float(answered.mean()) if answered.size else None,
            "per_press": per_press, "folds": fold_log,
            "invalid_fraction": float(np.mean(e >= INVALID_ERROR_DEG))}


def _cross_validate(make_model, samples: Samples, reference: np.ndarray, folds: int, seed: int,
                    judge: Samples | None = None, fold_hook=None):
    presses = np.unique(samples.press[(samples.press >= 0) & samples.contact])
    if len(presses) < 2:
        raise ValueError(f"cross_validate: needs at least two accepted presses, got {len(presses)}")
    assign = fold_assignment(presses, folds, seed)
    fold_of = np.array([assign.get(int(p), -1) for p in samples.press])
    judged = samples if judge is None else judge
    judged_fold = fold_of if judge is None else np.array([assign.get(int(p), -1) for p in judge.press])
    errors = np.full(len(judged), np.nan)
    pred = np.zeros((len(judged), 3))
    pred[:, 2] = 1.0
    valid = np.zeros(len(judged), bool)
    fold_log = []
    for f in sorted(set(assign.values())):
        test_p = sorted(p for p, g in assign.items() if g == f)
        train = fold_of != f
        model = make_model()
        model.fit(samples.subset(train), reference)
        test = (judged_fold == f) & judged.contact
        n, ok = model.predict(judged.subset(test))
        pred[test], valid[test] = n, ok
        e = angular_error_deg(n, judged.normals[test])
        errors[test] = np.where(ok & np.isfinite(e), e, INVALID_ERROR_DEG)
        if fold_hook is not None:
            fold_hook(model, test_p)
        fold_log.append({"test_presses": test_p,
                         "train_presses": sorted(int(p) for p in np.unique(samples.press[train]) if p >= 0)})
    return cv_report(errors, judged, fold_log), (pred, valid, np.isfinite(errors))
