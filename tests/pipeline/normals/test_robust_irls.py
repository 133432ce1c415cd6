"""The ``robust`` solver (explicit shadow and highlight models): closed-form recovery with
injected attached shadows, cast shadows and highlights; float32 against float64; hard cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.normals import solve_farfield, solve_robust_irls
from sim.far_field import dome_lights
from support_recon import _one_torch_thread, angular_error_deg  # noqa: F401


def _corrupted(seed=0, pixels=64, colour=True):
    """Exact Lambertian data of random normals under 96 dome lights (x RGB channels with
    per-light intensities when ``colour``), with attached shadows at 0 and, per pixel, some lit
    observations cast-shadowed (x 0.05) and some made highlights (x 2.5 to 4)."""
    rng = np.random.default_rng(seed)
    d, e = dome_lights()
    tilt = np.radians(rng.uniform(0, 60, pixels))
    az = rng.uniform(0, 2 * np.pi, pixels)
    n = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], -1)
    if colour:
        L = (d[:, None, :] * e[:, :, None]).reshape(-1, 3)  # (P*3, 3): light-major, channel-minor
        albedo = rng.uniform(0.3, 0.9, (pixels, 3))
        groups = np.tile(np.arange(3), len(d))
        rho = albedo[:, groups]  # (pixels, N)
    else:
        L, groups, rho = d, None, rng.uniform(0.3, 0.9, (pixels, 1))
    shading = n @ L.T  # (pixels, N)
    I = 1000.0 * rho * np.clip(shading, 0, None)
    light = np.arange(L.shape[0]) // (3 if colour else 1)  # which light each observation is
    bad = np.zeros_like(I, bool)
    for p in range(pixels):
        lit = np.unique(light[shading[p] > 0.1])
        pick = rng.choice(lit, size=10, replace=False)
        for j, lgt in enumerate(pick):  # whole lights: every channel of a light shadowed / glossy
            k = light == lgt
            I[p, k] *= 0.05 if j < 5 else rng.uniform(2.5, 4.0)
            bad[p, k] = True
    return I.T.reshape(-1, 1, pixels), L, groups, n[None], bad


@pytest.mark.parametrize("colour", [True, False])
@pytest.mark.parametrize("weight", ["tukey", "cauchy"])
def test_recovers_normals_exactly_despite_shadows_and_highlights(colour, weight):
    I, L, groups, n, bad = _corrupted(colour=colour)
    res = solve_robust_irls(I, L, groups=groups, dtype="float64", weight=weight)
    err = angular_error_deg(res.normals, n)
    # Tukey rejects the outliers outright: exact. Cauchy keeps a tiny weight on them.
    assert err.max() < (1e-6 if weight == "tukey" else 0.05), err.max()
    assert res.mask.all()
    ls = solve_farfield(I, L, groups=groups, dtype="float64")
    assert angular_error_deg(ls.normals, n).mean() > 2.0  # what the outliers do to least squares
    if weight == "tukey":  # exactly the good lit observations are kept
        lit_good = (I[:, 0, :] > 0) & ~bad.T
        assert (res.count[0] == lit_good.sum(0)).all()
        if colour:  # per-channel albedo (times the 1000 exposure) recovered
            assert res.albedo.shape == (1, 64, 3)


def test_float32_agrees_with_float64():
    from sim.ps_objects import render_ps_capture, sphere_object

    d, e = dome_lights(6, 8)
    rec = render_ps_capture(sphere_object((48, 48), 22), d, e, specular=0.04, roughness=0.3, seed=2)
    frames, mask = rec.data["frames"][0], rec.data["mask"]
    P = frames.shape[0]
    obs = frames.transpose(0, 3, 1, 2).reshape(P * 3, 48, 48)
    L = rec.data["lights/light_vectors"].reshape(P * 3, 3)
    kw = dict(groups=np.tile(np.arange(3), P), dark_threshold=655.35, saturation=65535.0, mask=mask)
    r32 = solve_robust_irls(obs, L, dtype="float32", **kw)
    r64 = solve_robust_irls(obs, L, dtype="float64", **kw)
    assert r32.normals.dtype == np.float32 and r64.normals.dtype == np.float64
    diff = angular_error_deg(r32.normals, r64.normals)[mask]
    # Rejection decisions at a threshold can flip on float rounding at a few pixels; the rest agree.
    assert np.median(diff) < 1e-3 and np.mean(diff) < 0.02, (np.median(diff), diff.mean())
    assert (r32.mask == r64.mask).all()
    truth = rec.data["truth/normals"][0]
    e32, e64 = angular_error_deg(r32.normals, truth)[mask].mean(), angular_error_deg(r64.normals, truth)[mask].mean()
    assert abs(e32 - e64) < 0.01 and e64 < 1.0


def test_hard_cases_stay_finite_and_are_masked():
    d, _ = dome_lights(3, 4)  # 12 lights
    n = np.array([0.3, -0.2, 0.93])
    n /= np.linalg.norm(n)
    good = np.clip(d @ n, 0, None) * 500.0
    cols = []
    cols.append(good)  # 0: clean
    two = np.zeros(12)
    two[:2] = good[:2]
    cols.append(two)  # 1: only two usable observations
    cols.append(np.zeros(12))  # 2: zero albedo (black)
    nan = good.copy()
    nan[[1, 4]] = np.nan
    nan[7] = np.inf
    cols.append(nan)  # 3: NaN and Inf among good observations
    cols.append(np.full(12, np.nan))  # 4: nothing finite
    cols.append(good * 1e30)  # 5: huge but finite
    three = np.zeros(12)
    idx = np.argsort(-good)[:3]
    three[idx] = good[idx]
    cols.append(three)  # 6: exactly three usable
    I = np.stack(cols, -1)[:, None, :]
    for dt in ("float32", "float64"):
        res = solve_robust_irls(I, d, dtype=dt)
        for k in ("normals", "albedo", "residual", "condition"):
            assert np.isfinite(getattr(res, k)).all(), (dt, k)
        m = res.mask[0]
        assert m[0] and m[3] and m[6], (dt, m)
        assert not m[1] and not m[2] and not m[4], (dt, m)
        assert (res.normals[0, ~m] == [0, 0, 1]).all() and (res.albedo[0, ~m] == 0).all()
        tol = 1e-3 if dt == "float32" else 1e-8
        assert angular_error_deg(res.normals[0, [0, 3, 6]], n).max() < tol
        assert res.count[0, 3] == 9 and res.count[0, 6] == 3


def test_rank_deficient_and_non_finite_lights_mask_pixels():
    L = np.array([[0.5, 0, 1.0], [-0.5, 0, 1.0], [0.0, 0, 1.0], [0.25, 0, 1.0]])  # all in the x-z plane
    I = (L @ [0.2, 0.0, 0.98])[:, None, None] * np.ones((4, 2, 3))
    res = solve_robust_irls(I, L)
    assert not res.mask.any() and (res.condition >= 1e3).all() and np.isfinite(res.normals).all()
    L2 = np.array([[0.5, 0, 1.0], [0, 0.5, 1.0], [-0.5, -0.5, 1.0], [0.3, 0.1, 1.0], [np.nan, 0, 1]])
    n = np.array([0.1, 0.2, 0.97])
    n /= np.linalg.norm(n)
    I2 = (np.nan_to_num(L2) @ n)[:, None, None] * np.ones((5, 2, 2))
    res = solve_robust_irls(I2, L2, dtype="float64")
    assert res.mask.all() and (res.count == 4).all()
    assert angular_error_deg(res.normals, n).max() < 1e-8


def test_per_pixel_lights_batches_and_integer_input_agree():
    I, L, groups, n, _ = _corrupted(seed=5, pixels=40)
    base = solve_robust_irls(I, L, groups=groups, dtype="float64")
    per_pixel = np.broadcast_to(L[:, None, None, :], (L.shape[0], 1, 40, 3))
    for other in (solve_robust_irls(I, per_pixel, groups=groups, dtype="float64"),
                  solve_robust_irls(I, L, groups=groups, dtype="float64", batch_elements=288 * 7)):
        np.testing.assert_allclose(other.normals, base.normals, atol=1e-9)
        np.testing.assert_array_equal(other.count, base.count)
    q = np.round(I).astype(np.uint16)
    a = solve_robust_irls(q, L, groups=groups, dtype="float64")
    b = solve_robust_irls(q.astype(np.float64), L, groups=groups, dtype="float64")
    np.testing.assert_array_equal(a.normals, b.normals)


def test_input_errors_name_the_function():
    with pytest.raises(ValueError, match=r"solve_robust_irls: lights must have shape \(3, 3\)"):
        solve_robust_irls(np.ones((3, 2, 2)), np.ones((4, 3)))
    with pytest.raises(ValueError, match="solve_robust_irls: weight must be one of"):
        solve_robust_irls(np.ones((3, 2, 2)), np.eye(3), weight="huber")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device in this environment")
def test_cuda_matches_cpu():
    I, L, groups, n, _ = _corrupted(seed=7, pixels=32)
    a = solve_robust_irls(I, L, groups=groups, dtype="float64", device="cpu")
    b = solve_robust_irls(I, L, groups=groups, dtype="float64", device="cuda")
    np.testing.assert_allclose(a.normals, b.normals, atol=1e-9)
