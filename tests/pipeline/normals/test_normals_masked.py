"""Solving only where asked: every solver's ``mask=`` equals its full-frame result on the mask,
marks the rest invalid (no NaN), and rejects bad masks with one clear error; integrators on a
region: sparse on the mask, rectangular ones on its bounding box."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.depth import integrate
from pipeline.normals import (
    FarFieldSolver,
    NearFieldSolver,
    PixelMask,
    solve_cauchy,
    solve_farfield,
    solve_nearfield,
    solve_robust_irls,
)
from pipeline.normals.masking import pixel_batches
from pipeline.normals.result import COND_CAP
from support_recon import NearestColourTable, _one_torch_thread, channel_groups, render_sphere_scene  # noqa: F401

FIELDS = ("normals", "albedo", "residual", "condition", "mask", "count")


@pytest.fixture(scope="module")
def scene():
    s = render_sphere_scene((24, 30), 0.2, radius=2.0, depth=0.5, num_patterns=6, noise=1.0, bits=8, seed=3)
    P, H, W, C = s.frames.shape
    obs = s.frames.transpose(0, 3, 1, 2).reshape(P * C, H, W)
    mask = np.random.default_rng(0).random((H, W)) < 0.4
    return s, obs, mask, channel_groups(P)


def _same_on_mask(full, masked, mask):
    for k in FIELDS:
        a, b = getattr(full, k), getattr(masked, k)
        assert a.shape == b.shape and a.dtype == b.dtype, k
        np.testing.assert_allclose(b[mask].astype(float), a[mask].astype(float), rtol=1e-7, atol=1e-7, err_msg=k)
    # Outside: invalid, the documented fill values, nothing NaN.
    out = ~mask
    assert not masked.mask[out].any() and (masked.count[out] == 0).all()
    assert (masked.normals[out] == [0, 0, 1]).all() and (masked.albedo[out] == 0).all()
    assert (masked.residual[out] == 0).all() and (masked.condition[out] == COND_CAP).all()
    for k in FIELDS:
        assert np.isfinite(getattr(masked, k).astype(float)).all(), k


# float64 so that the comparison sees the masking, not float32 summation order.
F64 = dict(dtype="float64")
SOLVERS = {
    "lstsq": lambda s, o, g, m: solve_farfield(o, s.lights_far(), groups=g, mask=m, **F64),
    "lstsq frames": lambda s, o, g, m: FarFieldSolver(s.lights_far(), groups=g, **F64).solve_frames(
        s.frames.astype(np.uint8), mask=m),
    "nearfield": lambda s, o, g, m: solve_nearfield(o, s.lights_flat(), groups=g, mask=m, **F64),
    "nearfield qr": lambda s, o, g, m: NearFieldSolver(s.lights_flat(), method="qr", mask=m, **F64).solve(o),
    "robust": lambda s, o, g, m: solve_robust_irls(o, s.lights_flat(), groups=g, dark_threshold=2.55, mask=m, **F64),
    "cauchy": lambda s, o, g, m: solve_cauchy(o, s.lights_flat(), groups=g, dark_threshold=2.55, mask=m, **F64),
}


@pytest.mark.parametrize("name", SOLVERS)
def test_masked_solve_equals_full_frame_on_the_mask(name, scene):
    s, obs, mask, g = scene
    _same_on_mask(SOLVERS[name](s, obs, g, None), SOLVERS[name](s, obs, g, mask), mask)


def test_gather_scatter_round_trip_and_bbox():
    m = np.zeros((5, 7), bool)
    m[1, 2] = m[3, 5] = True
    pm = PixelMask(m, (5, 7), "t")
    a = np.arange(2 * 5 * 7 * 3).reshape(2, 5, 7, 3)
    g = pm.gather(a, axis=1)
    assert g.shape == (2, 1, 2, 3) and g[1, 0, 1].tolist() == a[1, 3, 5].tolist()
    back = pm.scatter_array(g, fill=-1, axis=1)
    assert (back[:, m] == a[:, m]).all() and (back[:, ~m] == -1).all()
    assert pm.bbox() == (slice(1, 4), slice(2, 6)) and pm.bbox(10) == (slice(0, 5), slice(0, 7))
    import torch

    assert pm.gather(torch.as_tensor(a), axis=1).tolist() == g.tolist()


@pytest.mark.parametrize("bad, msg", [(np.ones((3, 3), bool), r"mask must have shape \(4, 5\).*got \(3, 3\)"),
                                      (np.zeros((4, 5), bool), "selects no pixels"),
                                      (np.full((4, 5), np.nan), "must be boolean")])
def test_bad_masks_are_one_clear_error(bad, msg):
    obs = np.ones((3, 4, 5))
    with pytest.raises(ValueError, match=msg):
        solve_farfield(obs, np.eye(3), mask=bad)
    with pytest.raises(ValueError, match=msg):
        solve_robust_irls(obs, np.eye(3), mask=bad)


def test_pixel_batches_cover_every_pixel_once():
    for M, N, e in [(1, 5, 100), (10, 4, 16), (1000, 288, 4096), (7, 1, 1)]:
        b = pixel_batches(M, N, e)
        assert b[0][0] == 0 and b[-1][1] == M and all(x[1] == y[0] for x, y in zip(b, b[1:]))
        assert max(hi - lo for lo, hi in b) <= max(1, e // N)


def _bump(shape=(40, 48), mm=0.1):
    from pipeline.base.frames import normals_from_height

    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    h = 0.3 * np.exp(-((xx - 20.0) ** 2 + (yy - 18.0) ** 2) / 30.0)
    return normals_from_height(h, mm), h


@pytest.mark.parametrize("method", ["fc", "dct", "dst"])
def test_rectangular_integrators_run_on_the_regions_bounding_box(method):
    n, _ = _bump()
    region = np.zeros(n.shape[:2], bool)
    region[8:30, 9:33] = True
    region[8, 9] = False  # not a rectangle: the box is still 8:30, 9:33
    out = integrate(n, 0.1, None, method=method, region=region)
    box = integrate(n[6:32, 7:35], 0.1, region[6:32, 7:35], method=method)  # the box grown by the 2-pixel margin
    np.testing.assert_allclose(out.height[region], box.height[2:-2, 2:-2][region[8:30, 9:33]], atol=1e-6)
    assert (out.height[~region] == 0).all() and (out.mask == region).all()
    assert out.meta["bbox"] == [6, 32, 7, 35]


def test_sparse_integrator_solves_on_the_region_and_full_region_changes_nothing():
    n, h = _bump()
    full = np.ones(n.shape[:2], bool)
    for method in ("sparse", "dst"):
        a = integrate(n, 0.1, None, method=method)
        b = integrate(n, 0.1, None, method=method, region=full)
        np.testing.assert_array_equal(a.height, b.height)
    disc = np.hypot(*np.mgrid[-20:20, -24:24]) < 15
    out = integrate(n, 0.1, None, method="sparse", region=disc)
    ref = integrate(n, 0.1, disc, method="sparse")
    np.testing.assert_allclose(out.height, np.where(disc, ref.height, 0), atol=1e-6)
    assert (out.mask == disc).all()
