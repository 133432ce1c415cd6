"""The benchmarks behind ``iristac bench NAME``, one module each, every one printing error and time
side by side (the list and the protocol a benchmark module keeps are in :mod:`pipeline.cli.bench`).

``all`` runs them in turn and writes the accuracy-against-time page (:mod:`pipeline.charts`);
``report`` and ``compare`` read saved runs. Helpers that only one benchmark uses are private
modules (``_calibration_sensors``, ``_calibration_split``).
"""
