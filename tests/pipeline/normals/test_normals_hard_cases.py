"""Hard cases: rank-deficient lights, dark/saturated/NaN/Inf observations (hypothesis), and
numerical agreement (float32 vs float64, numpy vs torch input, run-to-run, fast vs general)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.normals import FarFieldSolver, NearFieldSolver, solve_cauchy, solve_farfield, solve_nearfield
from support_recon import _one_torch_thread, angular_error_deg, channel_groups, render_sphere_scene  # noqa: F401

FIELDS = ("normals", "albedo", "residual", "condition")


def _assert_finite(res, shape):
    for name in FIELDS:
        a = getattr(res, name)
        assert a.shape[:2] == shape, name
        assert np.isfinite(a).all(), name
    assert res.mask.dtype == bool and res.mask.shape == shape
    np.testing.assert_allclose(np.linalg.norm(res.normals, axis=-1), 1.0, rtol=1e-5)
    # Invalid pixels carry the flat normal and zero albedo.
    assert (res.normals[~res.mask] == [0.0, 0.0, 1.0]).all()
    assert (res.albedo[~res.mask] == 0).all()


# Observation values with the special cases over-represented.
_values = st.one_of(st.sampled_from([0.0, 255.0, np.nan, np.inf, -np.inf, 1e30, -1.0]),
                    st.floats(0.0, 255.0))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lights=arrays(np.float64, st.tuples(st.integers(1, 6), st.just(3)),
                     elements=st.floats(-2, 2, allow_nan=False)),
       data=st.data(), solver=st.sampled_from(["far", "near", "robust"]))
def test_any_input_gives_finite_output_with_mask(lights, data, solver):
    N = lights.shape[0]
    I = data.draw(arrays(np.float64, (N, 3, 4), elements=_values))
    if solver == "far":
        res = solve_farfield(I, lights)
    elif solver == "near":
        res = solve_nearfield(I, np.broadcast_to(lights[:, None, None], (N, 3, 4, 3)))
    else:
        res = solve_cauchy(I, lights, dark_threshold=0.5, saturation=254.5)
    _assert_finite(res, (3, 4))
    # Fewer than three usable observations can never be valid.
    usable = np.isfinite(I)
    if solver == "robust":
        usable &= (I > 0.5) & (I < 254.5)
    assert not (res.mask & (usable.sum(0) < 3)).any()



@pytest.mark.parametrize("solver", ["far", "near"])
def test_huge_finite_observation_stays_finite(solver):
    """A 1e30 observation is finite, but its square overflows float32 (hypothesis found it):
    every output stays finite, the residual saturating instead of going to Inf."""
    L = np.full((6, 3), 8.1e-43)
    L[0, 2] = L[2, 0] = L[5, 1] = 1.0
    I = np.zeros((6, 3, 4))
    I[1, 0, 0] = 1e30
    res = (solve_farfield(I, L) if solver == "far"
           else solve_nearfield(I, np.broadcast_to(L[:, None, None], (6, 3, 4, 3))))
    _assert_finite(res, (3, 4))

@settings(max_examples=25, deadline=None)
@given(direction=arrays(np.float64, 3, elements=st.floats(-1, 1)),
       repeats=st.integers(3, 8), kind=st.sampled_from(["repeated", "coplanar"]),
       seed=st.integers(0, 2 ** 16))
def test_rank_deficient_lights_are_masked(direction, repeats, kind, seed):
    rng = np.random.default_rng(seed)
    d = direction + np.array([0.0, 0.0, 1.5])
    d /= np.linalg.norm(d)
    if kind == "repeated":
        L = np.repeat(d[None], repeats, 0) * rng.uniform(0.5, 2.0, (repeats, 1))
    else:  # all in the plane spanned by d and z: rank 2
        a, b = rng.uniform(-1, 1, (2, repeats))
        L = a[:, None] * d + b[:, None] * np.array([0.0, 0.0, 1.0])
    I = np.abs(rng.normal(100, 20, (repeats, 2, 3)))
    for res in (solve_farfield(I, L), solve_nearfield(I, np.broadcast_to(L[:, None, None], (repeats, 2, 3, 3))),
                solve_cauchy(I, L)):
        _assert_finite(res, (2, 3))
        assert not res.mask.any()
        assert (res.condition > 1e3).all()


def test_dark_and_saturated_pixels():
    L = np.array([[0.0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8]])
    I = np.full((4, 2, 2), 50.0)
    I[:, 0, 0] = 0.0  # black pixel: no albedo, no normal
    I[:, 0, 1] = 255.0  # fully saturated pixel
    I[:2, 1, 0] = 255.0  # two of four saturated: robust has only two left
    res = solve_cauchy(I, L, dark_threshold=0.0, saturation=255.0)
    assert res.mask.tolist() == [[False, False], [False, True]]
    assert res.count.tolist() == [[0, 0], [2, 4]]
    res = solve_farfield(I, L)
    assert not res.mask[0, 0]


def test_nan_at_one_pixel_leaves_the_others_untouched():
    s = render_sphere_scene((12, 16), 0.3, radius=2.0, depth=0.3, num_patterns=4, noise=1.0, seed=1)
    obs = s.observations.copy()
    ref = FarFieldSolver(s.lights_far(), dtype="float64").solve(obs)
    obs[2, 5, 5] = np.nan  # forces the per-pixel path for the whole frame
    res = FarFieldSolver(s.lights_far(), dtype="float64").solve(obs)
    keep = np.ones((12, 16), bool)
    keep[5, 5] = False
    np.testing.assert_allclose(res.normals[keep], ref.normals[keep], atol=1e-10)
    assert res.mask[5, 5] and res.count[5, 5] == obs.shape[0] - 1
    # Same for per-pixel lights, and a NaN light vector masks only its observation.
    L = s.lights_flat().copy()
    L[0, 3, 3] = np.nan
    res = NearFieldSolver(L, dtype="float64").solve(s.observations)
    assert res.count[3, 3] == obs.shape[0] - 1 and res.mask[3, 3] and np.isfinite(res.normals).all()


def test_float32_matches_float64_and_runs_repeat_exactly(device):
    s = render_sphere_scene((20, 24), 0.2, radius=2.0, depth=0.3, num_patterns=6, noise=1.0, bits=8, seed=2)
    g = channel_groups(6)
    obs8 = s.observations.astype(np.uint8)
    for make in (lambda dt: FarFieldSolver(s.lights_far(), groups=g, dtype=dt, device=device),
                 lambda dt: NearFieldSolver(s.lights_flat(), groups=g, dtype=dt, device=device)):
        r32, r64 = make("float32").solve(obs8), make("float64").solve(obs8)
        assert r32.normals.dtype == np.float32 and r64.normals.dtype == np.float64
        assert angular_error_deg(r32.normals, r64.normals).max() < 1e-3
        np.testing.assert_allclose(r32.albedo, r64.albedo, rtol=1e-4)
        np.testing.assert_allclose(r32.residual, r64.residual, atol=0.05)
        again = make("float32").solve(obs8)
        for name in FIELDS + ("mask", "count"):
            np.testing.assert_array_equal(getattr(again, name), getattr(r32, name))
        # torch input (on the device) gives the same as numpy input.
        rt = make("float32").solve(torch.as_tensor(obs8, device=device))
        np.testing.assert_array_equal(rt.normals, r32.normals)


def test_normal_equations_match_qr():
    s = render_sphere_scene((16, 20), 0.25, radius=2.0, depth=0.3, num_patterns=5, noise=1.0, seed=3)
    a = NearFieldSolver(s.lights_flat(), dtype="float64").solve(s.observations)
    b = NearFieldSolver(s.lights_flat(), dtype="float64", method="qr").solve(s.observations)
    assert angular_error_deg(a.normals, b.normals).max() < 1e-8
    np.testing.assert_allclose(a.residual, b.residual, rtol=1e-6)


def test_bad_shapes_name_the_shape():
    with pytest.raises(ValueError, match=r"expected 4 observations, got shape \(3, 2, 2\)"):
        FarFieldSolver(np.zeros((4, 3))).solve(np.zeros((3, 2, 2)))
    with pytest.raises(ValueError, match=r"got \(2, 2\)"):
        solve_farfield(np.zeros((2, 2)), np.eye(3))
    with pytest.raises(ValueError, match=r"\(3, 5, 5, 3\)"):
        solve_cauchy(np.zeros((3, 4, 4)), np.zeros((3, 5, 5, 3)))


@pytest.mark.parametrize("kind", ["clipped", "partial shadow"])
def test_robust_beats_least_squares_when_a_fifth_is_corrupted(kind):
    from pipeline.bench.reconstruct import _corrupt

    s = render_sphere_scene((30, 40), 0.4, radius=3.0, depth=0.5, num_patterns=8, noise=1.0, bits=8, seed=5)
    obs = _corrupt(s.frames.astype(np.uint8), kind, np.random.default_rng(0))
    g = channel_groups(8)
    ls = NearFieldSolver(s.lights_flat(), groups=g).solve(obs)
    rb = solve_cauchy(obs, s.lights_flat(), groups=g, dark_threshold=2.55, saturation=255.0)
    e_ls = angular_error_deg(ls.normals, s.normals).mean()
    e_rb = angular_error_deg(rb.normals, s.normals).mean()
    assert e_rb < 0.5 < 3.0 < e_ls, (e_rb, e_ls)


def test_chunked_frames_path_equals_whole_frame(monkeypatch):
    from pipeline.normals import _inputs

    s = render_sphere_scene((14, 18), 0.3, radius=2.0, depth=0.3, num_patterns=4, noise=1.0, bits=8, seed=6)
    frames = s.frames.astype(np.uint8)
    solver = FarFieldSolver(s.lights_far(), groups=channel_groups(4))
    whole = solver.solve(s.observations.astype(np.float32))  # float path: no chunking
    monkeypatch.setattr(_inputs, "CHUNK", 50)  # 252 pixels -> 6 chunks, the last one short
    for res in (solver.solve_frames(frames), solver.solve(s.observations.astype(np.uint8))):
        for name in FIELDS + ("mask", "count"):
            np.testing.assert_allclose(getattr(res, name), getattr(whole, name), rtol=1e-5, atol=1e-5)
