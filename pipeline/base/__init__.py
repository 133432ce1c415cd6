"""The base layer: what every other part of IrisTac stands on, and which imports nothing above it.

- :mod:`~pipeline.base.errors`: :class:`UserError`, the one-line errors the CLI prints;
- :mod:`~pipeline.base.frames`: every coordinate convention (optical and reconstruction
  frames, pixels, heights, normals);
- :mod:`~pipeline.base.hashing`: canonical encoding and hashing of stage parameters;
- :mod:`~pipeline.base.store`: record I/O (``write_record``/``read_record``) and the stage
  store, the one way anything reads or writes HDF5;
- :mod:`~pipeline.base.capture`: the typed view of a ``capture`` record and its one writer;
- :mod:`~pipeline.base.camera`: the camera interface shared by real and virtual cameras;
- :mod:`~pipeline.base.modes`: lighting modes (the one pattern type, and the mode files);
- :mod:`~pipeline.base.registry`: the registries of solvers and integrators;
- :mod:`~pipeline.base.threads`: the one thread-limit helper;
- :mod:`~pipeline.base.lazy`: a package's names imported on first use (PEP 562).

Modules here import only the standard library, numpy, torch, h5py, yaml, jsonschema,
:mod:`data_schemas` and each other (``tests/test_layers.py`` checks it).
"""
