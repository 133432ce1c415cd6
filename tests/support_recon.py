"""Test support for the reconstruction tests (normals, depth, reconstruct, DiLiGenT, eval).

One place for: a single-thread torch fixture (the 2-core CI
box is shared; torch's spinning worker threads collapse under contention), angular error,
and a LookupTable-compatible table built from exact data (until calibration's lands).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipeline.base.threads import limit_threads
from pipeline.bench.recon_scene import render_sphere_scene, sphere_cap  # noqa: F401  (re-exported)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    with limit_threads(torch=1):
        yield


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-pixel angle (degrees) between unit normals ``(..., 3)`` (atan2: exact near 0)."""
    from pipeline.results.evaluate import angular_error_deg as ang

    return ang(a, b)


def channel_groups(num_patterns: int) -> np.ndarray:
    """Albedo group (camera channel) of each of ``P * 3`` observations, pattern-major."""
    return np.tile(np.arange(3), num_patterns)


class NearestColourTable:
    """A LookupTable-compatible object: nearest RGB among known (colour, gradient) samples.

    Built from exact data (a rendered calibration sphere), it is what the calibration
    stage's table does in its simplest form: ``lookup(images (N, H, W, 3)) -> (gradients
    (N, H, W, 2), valid (N, H, W))``. A pixel is valid when its colour lies within
    ``max_distance`` of a sample.
    """

    def __init__(self, colours: np.ndarray, gradients: np.ndarray, max_distance: float):
        self.tree = cKDTree(np.asarray(colours, float).reshape(-1, 3))
        self.gradients = np.asarray(gradients, float).reshape(-1, 2)
        self.max_distance = float(max_distance)

    def lookup(self, images):
        images = np.asarray(images, float)
        d, i = self.tree.query(images.reshape(-1, 3))
        g = self.gradients[i].reshape(images.shape[:-1] + (2,))
        return g, (d <= self.max_distance).reshape(images.shape[:-1])


def uint8_sphere_scene(shape=(36, 52), patterns=6, seed=0, coloured=False):
    """A rendered sphere press as 8-bit frames ``(P, H, W, 3)``, its lights ``(P, 3, H, W, 3)``
    (``coloured``: each channel its own lights, so the per-group albedo alternation runs) and
    the scene."""
    scene = render_sphere_scene(shape, 0.1, radius=1.5, depth=0.4, num_patterns=patterns, peak=200.0, noise=1.0,
                                bits=8, seed=seed)
    lights = scene.lights.copy()
    if coloured:  # channels see different lights: the per-group albedo alternation runs
        rng = np.random.default_rng(seed)
        lights = lights * rng.uniform(0.7, 1.3, size=(patterns, 3, 1, 1, 3))
    return scene.frames.astype(np.uint8), lights, scene
