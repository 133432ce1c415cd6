"""Every normal solver on closed-form scenes: a tilted plane and a sphere cap, exact data, in
float32 and float64 (``dtype``) on every device (``device``)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.base.frames import gradients_to_normals, normals_to_gradients
from pipeline.normals import (
    FarFieldSolver,
    NearFieldSolver,
    ratio_to_reference,
    solve_cauchy,
    solve_farfield,
    solve_nearfield,
)
from support_recon import NearestColourTable, _one_torch_thread, angular_error_deg, channel_groups, render_sphere_scene  # noqa: F401

LIGHTS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8], [0.0, -0.6, 0.8],
                   [0.4, 0.4, 0.82]])


def _plane(shape=(6, 7)):
    n = gradients_to_normals(np.full(shape, 0.3), np.full(shape, -0.2))
    return n


@pytest.fixture(scope="module")
def sphere():
    """Noiseless sphere indentation under 6 sectors of the bare ring (no attached shadows)."""
    return render_sphere_scene((30, 40), 0.12, radius=2.0, depth=0.3, num_patterns=6)


def test_farfield_plane_exact_with_albedo(device, dtype):
    n = _plane()
    rho = 0.7
    I = rho * np.einsum("kc,hwc->khw", LIGHTS, n)
    res = solve_farfield(I, LIGHTS, dtype=dtype.name, device=device)
    assert res.mask.all()
    assert angular_error_deg(res.normals, n).max() < dtype.tol(1e-6, 1e-3)
    np.testing.assert_allclose(res.albedo[..., 0], rho, rtol=dtype.tol(1e-9, 1e-5))
    assert res.residual.max() < dtype.tol(1e-6, 1e-5)
    np.testing.assert_allclose(res.condition, np.linalg.cond(LIGHTS), rtol=dtype.tol(1e-6, 1e-4))
    assert (res.count == len(LIGHTS)).all()


def test_farfield_sphere_exact_per_channel_albedo(sphere, device, dtype):
    # Coloured patterns: each camera channel sees its own light direction, and the albedo is
    # coloured, so a joint solve is biased; the per-channel alternation converges to the truth.
    rng = np.random.default_rng(7)
    P = 6
    L = np.concatenate([rng.normal(0, 0.5, (P * 3, 2)), rng.uniform(0.8, 1.2, (P * 3, 1))], axis=1)
    rho = np.array([0.9, 0.5, 0.2])
    I = np.einsum("kc,hwc->khw", L, sphere.normals) * np.tile(rho, P)[:, None, None]
    kw = dict(groups=channel_groups(P), dtype=dtype.name, device=device)
    joint = solve_farfield(I, L, albedo_iterations=0, **kw)
    e_joint = angular_error_deg(joint.normals, sphere.normals).max()
    assert e_joint > 1.0
    auto = solve_farfield(I, L, **kw)  # detects differing lights
    assert angular_error_deg(auto.normals, sphere.normals).max() < e_joint / 10
    res = solve_farfield(I, L, albedo_iterations=30, **kw)
    assert res.mask.all()
    assert angular_error_deg(res.normals, sphere.normals).max() < dtype.tol(1e-3, 1e-2)
    np.testing.assert_allclose(res.albedo / res.albedo[..., :1], np.broadcast_to(rho / rho[0], res.albedo.shape),
                               rtol=dtype.tol(1e-4, 1e-3))


@pytest.mark.parametrize("method", ["normal", "qr"])
def test_nearfield_sphere_exact(sphere, method, device, dtype):
    P = sphere.frames.shape[0]
    res = solve_nearfield(sphere.observations, sphere.lights_flat(), groups=channel_groups(P), method=method,
                          dtype=dtype.name, device=device)
    assert res.mask.all()
    assert angular_error_deg(res.normals, sphere.normals).max() < dtype.tol(1e-4, 1e-2)
    # The scene's light vectors carry rho: the recovered albedo is the gel's RGB albedo.
    np.testing.assert_allclose(res.albedo, sphere.albedo, rtol=dtype.tol(1e-4, 1e-4))
    assert res.residual.max() < dtype.tol(1e-6, 1e-3) * sphere.frames.max()


def test_nearfield_plane_exact(device, dtype):
    rng = np.random.default_rng(3)
    n = _plane((5, 4))
    L = rng.normal(size=(7, 5, 4, 3))
    L[..., 2] = np.abs(L[..., 2]) + 1.0
    I = 2.5 * np.einsum("khwc,hwc->khw", L, n)
    res = NearFieldSolver(L, dtype=dtype.name, device=device).solve(I)
    assert res.mask.all() and angular_error_deg(res.normals, n).max() < dtype.tol(1e-6, 1e-3)
    np.testing.assert_allclose(res.albedo[..., 0], 2.5, rtol=dtype.tol(1e-9, 1e-5))


@pytest.mark.parametrize("method", ["irls", "trim"])
def test_robust_plane_and_sphere_exact(sphere, method, device, dtype):
    n = _plane()
    I = np.einsum("kc,hwc->khw", LIGHTS, n)
    kw = dict(method=method, dtype=dtype.name, device=device, trim_low=0.0, trim_high=0.0)
    res = solve_cauchy(I, LIGHTS, **kw)
    assert res.mask.all() and angular_error_deg(res.normals, n).max() < dtype.tol(1e-6, 1e-3)
    res = solve_cauchy(sphere.observations, sphere.lights_flat(), groups=channel_groups(sphere.frames.shape[0]), **kw)
    assert res.mask.all() and angular_error_deg(res.normals, sphere.normals).max() < dtype.tol(1e-4, 1e-2)


def test_ratio_to_reference_cancels_albedo_and_vignetting(sphere, device, dtype):
    # Albedo that varies over the image and a vignetting gain: both multiply contact and
    # reference frames alike, so the ratio solve recovers the exact normals with albedo 1.
    P = sphere.frames.shape[0]
    H, W = sphere.normals.shape[:2]
    yy, xx = np.mgrid[0:H, 0:W]
    gain = (0.5 + 0.5 * np.cos((xx - W / 2) / W * 2)) * (0.6 + 0.4 * yy / H)
    obs = sphere.observations * gain
    ref = sphere.reference.transpose(0, 3, 1, 2).reshape(P * 3, H, W) * gain
    r, Lr = ratio_to_reference(obs, ref, sphere.lights_flat())
    res = solve_nearfield(r, Lr, dtype=dtype.name, device=device)
    assert res.mask.all()
    assert angular_error_deg(res.normals, sphere.normals).max() < dtype.tol(1e-4, 1e-2)
    np.testing.assert_allclose(res.albedo[..., 0], 1.0, rtol=dtype.tol(1e-6, 1e-4))


def test_solvers_agree_on_sign_convention(device, dtype):
    # A pixel lit more by the +x light tilts its normal toward +x: n_x > 0 (pipeline.base.frames).
    I = np.einsum("kc,c->k", LIGHTS, [0.3, 0.0, 0.95])[:, None, None]
    res = FarFieldSolver(LIGHTS, dtype=dtype.name, device=device).solve(I)
    p, q = normals_to_gradients(res.normals[0, 0])
    assert res.normals[0, 0, 0] > 0 and p < 0
