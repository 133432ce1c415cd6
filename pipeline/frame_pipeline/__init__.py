"""Frame pipelines: camera frames to normals and heights together, a run of frames at a time.

- :mod:`~pipeline.frame_pipeline.outputs`: what a reconstruction writes (:class:`OutputSpec`:
  the datasets, their precision) and the layouts of the files that hold them;
- :mod:`~pipeline.frame_pipeline.chunk`: :class:`FramePipeline`, the one per-frame pipeline
  ``iristac live``, ``reconstruct`` and ``batch`` run (a solver's fast path or its eager solve,
  then the integrator's, then the contact mask), on the threads of one
  :class:`~pipeline.base.frame_pool.FramePool`;
- :mod:`~pipeline.frame_pipeline.device`: :class:`DeviceFramePipeline`, the same on a torch
  device a chunk at a time (``batch --device cuda``);
- :mod:`~pipeline.frame_pipeline.cpu_batch`: :class:`CPUFramePipeline`, near-field normals and
  DST heights of many frames on every CPU core, each thread a run of frames per kernel call;
- :mod:`~pipeline.frame_pipeline.gpu_stream`: :class:`GPUFramePipeline`, the same on a CUDA
  device, the uploads overlapped with the solve.

Each runs a normals solver (:mod:`pipeline.normals`) and then an integrator
(:mod:`pipeline.depth`): what needs both lives here, so neither of those imports the other.

The solvers it runs are built a layer above (:func:`pipeline.solving.frame_solvers.frame_solver`);
this package knows no calibration object.
"""

from pipeline.base.lazy import lazy_names

__all__ = ["FramePipeline", "FrameBatch", "OutputSpec", "OUTPUT_CHOICES", "PRECISIONS", "DeviceFramePipeline",
           "CPUFramePipeline", "GPUFramePipeline"]

__getattr__, __dir__ = lazy_names(__name__, {"FramePipeline": "chunk", "FrameBatch": "chunk", "OutputSpec": "outputs",
                                             "OUTPUT_CHOICES": "outputs", "PRECISIONS": "outputs",
                                             "DeviceFramePipeline": "device", "CPUFramePipeline": "cpu_batch", "GPUFramePipeline": "gpu_stream"},
                                  globals())
