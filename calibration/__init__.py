"""calibration: sphere-indentation calibration (contact detection, ground truth, light models, LUT, MLP).

The public entry points (importable from ``calibration``, each loaded on first use: the models
load torch):

- imports of other formats into a capture: :func:`load_images` (a folder of images or a video),
  :func:`load_gelsight_npz` (:mod:`calibration.importers`);
- stage 2, calibrate: :class:`CalibrationResult`, :func:`find_circles` (the stage itself is
  :func:`calibration.calibrate.calibrate`, named like its module); a stored calibration: :func:`load_calibration`,
  :func:`load_models` (:mod:`calibration.stored`);
- contact detection: :func:`detect_contacts`, :class:`DetectOptions` (:mod:`calibration.detect`);
- a new unit from a few presses and another unit's calibration: :func:`calibrate_with_prior`
  (:mod:`calibration.prior`);
- judging a calibration on presses it never saw: :func:`evaluate_calibration`
  (:mod:`calibration.evaluate`), the truth-free ball check :func:`ball_fit`
  (:mod:`calibration.ballfit`);
- printed gel markers: :func:`detect_markers`, :func:`resolve_markers` (:mod:`calibration.markers`).

The fitted models themselves are in :mod:`calibration.models`.
"""

from pipeline.base.lazy import lazy_names

_WHERE = {"load_images": "importers", "load_gelsight_npz": "importers",
          "CalibrationResult": "calibrate", "find_circles": "calibrate",
          "load_calibration": "stored", "load_models": "stored",
          "detect_contacts": "detect", "DetectOptions": "detect",
          "calibrate_with_prior": "prior",
          "evaluate_calibration": "evaluate", "ball_fit": "ballfit",
          "detect_markers": "markers", "resolve_markers": "markers"}
__getattr__, __dir__ = lazy_names(__name__, _WHERE, globals())

__all__ = list(_WHERE)
