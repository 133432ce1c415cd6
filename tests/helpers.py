"""Test helpers shared across the suite."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def run_cli(*args, cwd=None, env=None, timeout=300, input=None) -> subprocess.CompletedProcess:
    """Run ``iristac ARGS...`` in a subprocess (``python -m pipeline``, this checkout's code)."""
    full_env = dict(os.environ)
    full_env["PYTHONPATH"] = str(REPO) + os.pathsep + full_env.get("PYTHONPATH", "")
    if env:
        full_env.update(env)
    return subprocess.run(
        [sys.executable, "-m", "pipeline", *map(str, args)],
        cwd=cwd or REPO,
        env=full_env,
        capture_output=True,
        text=True,
        timeout=timeout,
        input=input,
    )


def calibration_samples(cap, truth):
    """Samples of a synthetic sphere capture's presses at their detected circles, and the reference
    (linear frames, 8-bit saturation): what the calibration models' tests fit on."""
    from calibration.detect import detect_contacts
    from calibration.samples import collect_samples

    f, r = cap.linear()
    circles = detect_contacts(f, r, truth.ball_radius_mm / cap.mm_per_px)
    return collect_samples(f, r, circles, truth.ball_radius_mm, cap.mm_per_px, saturation=255), r


def wait_until(cond, timeout: float = 10.0) -> None:
    """Poll ``cond()`` until it holds (a camera's queue filled, a counter moved), failing after
    ``timeout`` seconds: tests wait for a thread's state, never for a sleep that a loaded machine
    (a second test worker) can outlast."""
    t = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < t, "timed out"
        time.sleep(0.002)
