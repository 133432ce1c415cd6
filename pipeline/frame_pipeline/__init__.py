"""Frame pipelines: camera frames to normals and heights together, a run of frames at a time.

- :mod:`~pipeline.frame_pipeline.outputs`: what a reconstruction writes (:class:`OutputSpec`:
  the datasets, their precision) and the layouts of the files that hold them;
- :mod:`~pipeline.frame_pipeline.chunk`: :class:`FramePipeline`, the one per-frame pipeline
  ``iristac live``, ``reconstruct`` and ``batch`` run (a solver's fast path or its eager solve,
  then the integrator's, then the contact mask), on the threads of one
  :class:`~pipeline.base.frame_pool.FramePool`.

The solvers it runs are built by the stage layer (:func:`pipeline.stages.fast_solvers.frame_solver`);
this package knows no calibration object.
"""

from pipeline.base.lazy import lazy_names

__all__ = ["FramePipeline", "FrameBatch", "OutputSpec", "OUTPUT_CHOICES", "PRECISIONS"]

__getattr__, __dir__ = lazy_names(__name__, {"FramePipeline": "chunk", "FrameBatch": "chunk", "OutputSpec": "outputs",
                                             "OUTPUT_CHOICES": "outputs", "PRECISIONS": "outputs"}, globals())
