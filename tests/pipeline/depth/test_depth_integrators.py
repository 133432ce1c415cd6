"""Depth integrators: closed-form plane and sphere (from float32 and float64 normals: ``dtype``),
agreement, sign, non-integrable fields, NaN/grazing normals, float32 vs float64."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.base.frames import gradients_to_normals, normals_from_height
from pipeline.base.registry import INTEGRATORS
from pipeline.depth import frankot_chellappa, integrate, poisson_dct, poisson_dst, sparse_lstsq
from support_recon import sphere_cap

S = 0.1  # mm per pixel
METHODS = list(INTEGRATORS.names())


def _plane(shape=(20, 24), p=0.3, q=-0.2):
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    # z = p x + q y with x = col * s, y = -row * s (pipeline.base.frames)
    h = p * cols * S + q * (-rows * S)
    return h, gradients_to_normals(np.full(shape, p), np.full(shape, q))


def _centered(h, ref):
    return h - np.mean(h - ref)


@pytest.mark.parametrize("method", ["fc", "dct", "sparse"])
def test_plane_is_exact(method, dtype):
    h, n = _plane()
    out = integrate(n.astype(dtype.np), S, method=method)
    np.testing.assert_allclose(_centered(out.height, h), h, atol=1e-5)
    assert out.mask.all() and out.height.dtype == np.float32


def test_dst_plane_exact_with_its_boundary_and_flat_border_by_default(dtype):
    h, n = _plane()
    out = poisson_dst(n.astype(dtype.np), S, boundary=h)
    np.testing.assert_allclose(out.height, h, atol=1e-5)
    # Default: zero height at the image edge. A bump flat near the border stays at zero there.
    hb, nb = sphere_cap((30, 30), S, 1.0, 0.3)
    out = poisson_dst(nb.astype(dtype.np), S)
    border = np.ones(hb.shape, bool)
    border[1:-1, 1:-1] = False
    assert np.abs(out.height[border]).max() < 1e-4


@pytest.mark.parametrize("method", METHODS)
def test_sphere_indentation_height_and_sign(method, dtype):
    # A 2 mm ball pressed 0.3 mm into the gel: a positive bump (toward the camera).
    h, n = sphere_cap((48, 56), S, 2.0, 0.3)
    out = integrate(n.astype(dtype.np), S, method=method)
    rmse = np.sqrt(np.mean((out.height - h) ** 2))
    assert rmse < 0.02 * 0.3, rmse
    assert abs(out.height.max() - 0.3) < 0.02 and out.height[24, 28] > 0.25


def test_dct_and_masked_sparse_solve_the_same_problem_on_a_full_mask():
    rng = np.random.default_rng(0)
    h, _ = sphere_cap((30, 34), S, 2.0, 0.3)
    n = normals_from_height(h + 0.01 * rng.normal(size=h.shape), S)  # not exactly integrable
    a = poisson_dct(n, S).height
    b = sparse_lstsq(n, S, rtol=1e-10).height
    np.testing.assert_allclose(a, b, atol=1e-5)


def test_sparse_ignores_everything_outside_the_mask(dtype):
    h, n = _plane((16, 18))
    n = n.astype(dtype.np)
    mask = np.zeros(h.shape, bool)
    mask[3:13, 4:15] = True
    n[~mask] = [0.9, -0.3, 0.3]  # garbage outside: must not matter
    n[~mask] /= np.linalg.norm(n[~mask], axis=-1, keepdims=True)
    out = sparse_lstsq(n, S, mask)
    assert (out.height[~mask] == 0).all() and (out.mask == mask).all()
    np.testing.assert_allclose(_centered(out.height[mask], h[mask]), h[mask], atol=1e-5)
    assert out.meta["converged"]


@settings(max_examples=20, deadline=None)
@given(field=arrays(np.float64, st.tuples(st.integers(3, 12), st.integers(3, 12), st.just(2)),
                    elements=st.floats(-5, 5)),
       method=st.sampled_from(METHODS))
def test_non_integrable_field_stays_bounded(field, method):
    # Random gradients (curl != 0): the least-squares height is bounded by the path length
    # times the largest slope.
    n = gradients_to_normals(field[..., 0], field[..., 1])
    out = integrate(n, S, method=method)
    H, W = field.shape[:2]
    bound = (H + W) * S * np.abs(field).max() + 1e-9
    assert np.isfinite(out.height).all()
    assert np.abs(out.height).max() <= bound


@settings(max_examples=20, deadline=None)
@given(normals=arrays(np.float64, (6, 7, 3), elements=st.one_of(
    st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 1e-12]), st.floats(-1, 1))),
       method=st.sampled_from(METHODS))
def test_garbage_normals_give_finite_heights_and_masks(normals, method):
    out = integrate(normals, S, method=method)
    assert np.isfinite(out.height).all()
    bad = ~np.isfinite(normals).all(-1) | ~(np.nan_to_num(normals[..., 2]) > 0)
    assert not out.mask[bad].any()


@pytest.mark.parametrize("method", METHODS)
def test_float32_normals_match_float64(method):
    h, n = sphere_cap((24, 28), S, 2.0, 0.3)
    a = integrate(n, S, method=method).height
    b = integrate(n.astype(np.float32), S, method=method).height
    np.testing.assert_allclose(a, b, atol=1e-5)
    np.testing.assert_array_equal(a, integrate(n, S, method=method).height)  # repeatable


def test_bad_input_messages():
    with pytest.raises(ValueError, match=r"got \(4, 4\)"):
        frankot_chellappa(np.zeros((4, 4)), S)
    with pytest.raises(ValueError, match="mm_per_px"):
        poisson_dct(np.zeros((4, 4, 3)), 0.0)
    with pytest.raises(ValueError, match="method must be one of"):
        integrate(np.zeros((4, 4, 3)), S, method="nope")
