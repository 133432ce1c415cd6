"""What ``reconstruct --solver lstsq`` imports: the far-field solve runs on its compiled fast path
on the CPU (numpy and Numba), so a one-shot reconstruction never pays torch's import (1-3 s, most
of the command's start)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from helpers import REPO

_PROBE = """
import json, sys
from pipeline.cli import main
rc = main(sys.argv[1:])
print(json.dumps({"rc": rc, "loaded": sorted(m for m in ("torch", "pipeline.normals.fast") if m in sys.modules)}))
"""


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    from sim.ps_objects import write_ps_capture

    path = tmp_path_factory.mktemp("startup") / "sphere.h5"
    write_ps_capture(path, "sphere", size=32, radius_px=12.0, lights=(3, 4), specular=0.0, seed=1)
    return path


def _run(capture, tmp_path, *args):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    argv = ["reconstruct", str(capture), "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "out"), "--json",
            *args]
    r = subprocess.run([sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    *report, probe = r.stdout.strip().splitlines()
    return json.loads("\n".join(report)), json.loads(probe)


def test_lstsq_reconstruct_runs_without_torch(capture, tmp_path):
    """The whole command (CLI, capture, far-field solve, DST depth, PNG/PLY outputs) on the CPU."""
    report, probe = _run(capture, tmp_path, "--solver", "lstsq")
    assert probe["rc"] == 0 and not report["cached"]
    assert probe["loaded"] == ["pipeline.normals.fast"], "torch was imported on the lstsq CPU path"
    assert report["valid_fraction"] > 0.3 and report["normal_mean_error_deg"] < 5.0  # it did solve the sphere
