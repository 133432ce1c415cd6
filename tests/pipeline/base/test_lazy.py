"""Lazy package names (``pipeline.base.lazy``): the live fast paths start without torch."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from helpers import REPO

_PROBE = """
import json, sys
import pipeline.live, pipeline.solving.frame_solvers, pipeline.normals.fast, pipeline.normals.fast_models
import pipeline.depth.fast, pipeline.base.store
print(json.dumps(sorted(m for m in ("torch", "scipy.sparse", "sim.render") if m in sys.modules)))
"""


def test_live_fast_paths_import_without_torch():
    """A camera's live start imports the fast paths only: torch (about a second) stays out."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1]) == []


def test_lazy_names_resolve_and_list():
    import pipeline.depth as depth
    import pipeline.normals as normals
    from pipeline.normals.result import NormalResult

    assert normals.NormalResult is NormalResult and "solve_nearfield" in dir(normals)
    assert callable(depth.poisson_dst) and "sparse_lstsq" in dir(depth)
    for name in normals.__all__:
        assert getattr(normals, name) is not None
    with pytest.raises(AttributeError, match="pipeline.normals.*no_such"):
        normals.no_such
