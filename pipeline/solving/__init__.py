"""What a capture's frames need before they are solved, shared by the normals stage, the streaming
reconstruction (``reconstruct``, ``batch``) and ``iristac live``, and so below all three:

- :mod:`~pipeline.solving.light_files`: the light model from a calibration, an illumination
  model or the capture itself (:func:`load_lights`, :func:`capture_lights`);
- :mod:`~pipeline.solving.regions`: the pixels to solve, the printed markers to fill in and the
  no-contact reference (:func:`capture_region`, :func:`marker_mask`, :func:`reference_frames`);
- :mod:`~pipeline.solving.frame_solvers`: the one place that chooses how a solver solves
  frames (its fast path, else its eager path: :func:`frame_solver`);
- :mod:`~pipeline.solving.model_solvers`: the calibration's fitted models as solvers of the
  registry.

This package sits in the calibration layer: a calibration's models are among the lights it loads.
"""

from pipeline.base.lazy import lazy_names

_WHERE = {"load_lights": "light_files", "capture_lights": "light_files",
          "capture_region": "regions", "marker_mask": "regions", "reference_frames": "regions",
          "frame_solver": "frame_solvers", "solve_with_model": "model_solvers"}
__getattr__, __dir__ = lazy_names(__name__, _WHERE, globals())

__all__ = list(_WHERE)
