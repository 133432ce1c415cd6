"""The entry points behind the commands, each a documented function the thin CLI calls (imported
from its module: the modules are named after the commands, so the package re-exports nothing):

- :func:`run_pipeline` (``iristac run CONFIG.yaml``: the five stages from a config file,
  :mod:`~pipeline.workflows.run`);
- :func:`reconstruct` (``iristac reconstruct``: normals and depth of one capture,
  :mod:`~pipeline.workflows.reconstruct`);
- :func:`batch_reconstruct` (``iristac batch``: many recordings, serially, on local workers or a
  Dask cluster, :mod:`~pipeline.workflows.batch`; the task pool it uses is
  :mod:`~pipeline.workflows.task_pool`);
- :func:`compare_modes` (``iristac compare-modes``: lighting modes by reconstruction error,
  :mod:`~pipeline.workflows.compare_modes`);
- :func:`run_demo` (``iristac demo``, :mod:`~pipeline.workflows.demo`).

``iristac live`` is :mod:`pipeline.live`; the engine that ``reconstruct`` and ``batch`` share is
:mod:`pipeline.streaming`.
"""
