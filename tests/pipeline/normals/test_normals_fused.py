"""The real-time far-field path (pipeline.normals.fused): the same numbers as the general
solver, eagerly (cheap) and under torch.compile (one small image per test: compiling costs a
few seconds), masks on degenerate input, and the fallback when compilation is impossible."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from pipeline.normals import FarFieldSolver, fused
from support_recon import _one_torch_thread, channel_groups, render_sphere_scene  # noqa: F401

FIELDS = ("normals", "albedo", "residual", "condition", "mask", "count")


@pytest.fixture(scope="module")
def scene():
    return render_sphere_scene((18, 22), 0.3, radius=2.0, depth=0.3, num_patterns=4, noise=1.0, bits=8, seed=3)


def _kernel_inputs(solver: FarFieldSolver):
    """The kernel's tensors from a solver's precomputed arrays (numpy on the CPU: the general
    solver runs there without torch)."""
    return (torch.as_tensor(solver.L), torch.as_tensor(solver.inv).reshape(3, 3),
            torch.as_tensor(solver.Q).reshape(-1, 3, 3), solver.group_tuple)


def _eager(solver: FarFieldSolver, obs: np.ndarray, usable: bool = True):
    N, H, W = obs.shape
    planes = list(torch.as_tensor(obs).reshape(N, H * W).unbind(0))
    L, inv, Q, groups = _kernel_inputs(solver)
    n, rho, res, ok = fused.farfield_pixels(planes, L, inv, Q, groups, usable)
    return n.numpy().reshape(H, W, 3), rho.numpy().reshape(H, W, -1), res.numpy().reshape(H, W), ok.numpy().reshape(H, W)


def _assert_same(a, b, atol=1e-4, mean_square=255.0 ** 2):
    """Equal to float32 rounding. The residual is ``sqrt(S - explained)``, a difference of sums
    of squares, so two summation orders agree in ``residual**2`` to a few ulps of ``S``
    (``mean_square`` bounds the observations' mean square), not in the residual itself."""
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if name == "residual":
            x, y, atol_sq = x.astype(np.float64) ** 2, y.astype(np.float64) ** 2, 1e-6 * mean_square + atol
            np.testing.assert_allclose(x, y, rtol=0, atol=atol_sq, err_msg=name)
        else:
            np.testing.assert_allclose(x, y, rtol=1e-5, atol=atol, err_msg=name)


@pytest.mark.parametrize("groups", [None, "rgb"])
def test_kernel_equals_general_solver_in_float64(scene, groups):
    """The unrolled per-pixel arithmetic is the general solver's mathematics, to float64 rounding."""
    g = channel_groups(4) if groups else None
    solver = FarFieldSolver(scene.lights_far(), groups=g, dtype="float64")
    obs = scene.observations.astype(np.float64)
    ref = solver.solve(obs)
    n, rho, res, ok = _eager(solver, obs)
    np.testing.assert_allclose(n, ref.normals, atol=1e-12)
    np.testing.assert_allclose(rho, ref.albedo, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res, ref.residual, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(ok, ref.mask)


def test_kernel_recovers_a_sphere_exactly():
    """Noise-free float observations of a sphere: the kernel returns its normals and albedo."""
    s = render_sphere_scene((16, 16), 0.3, radius=2.0, depth=0.4, num_patterns=4, noise=0.0, bits=None, seed=0)
    solver = FarFieldSolver(s.lights_far(), dtype="float64")
    exact = np.einsum("nc,hwc->nhw", s.lights_far(), s.normals)  # far-field images of unit albedo
    n, rho, res, ok = _eager(solver, exact)
    assert ok.all()
    np.testing.assert_allclose(n, s.normals, atol=1e-9)
    np.testing.assert_allclose(rho, 1.0, atol=1e-9)
    # The residual is sqrt(S - explained): a difference of moments, so its floor is the square
    # root of their rounding (~1e-6 of the observations' scale in float64), not 0.
    assert res.max() < 1e-5 * np.sqrt(np.mean(exact ** 2))


def test_kernel_masks_black_pixels_and_unusable_lights(scene):
    solver = FarFieldSolver(scene.lights_far(), groups=channel_groups(4), dtype="float64")
    obs = scene.observations.astype(np.float64)
    obs[:, 2, 3] = 0.0  # a black pixel has no normal
    n, rho, res, ok = _eager(solver, obs)
    assert not ok[2, 3] and ok.sum() == ok.size - 1
    assert n[2, 3].tolist() == [0.0, 0.0, 1.0] and (rho[2, 3] == 0).all() and res[2, 3] == 0
    n, rho, res, ok = _eager(solver, obs, usable=False)  # rank-deficient light matrix
    assert not ok.any() and (n == [0.0, 0.0, 1.0]).all() and (rho == 0).all() and (res == 0).all()


def test_frame_planes_cv2_numpy_and_torch_agree():
    rng = np.random.default_rng(0)
    for dtype in (np.uint8, np.uint16, np.float32):
        frames = (rng.random((3, 5, 7, 3)) * 200).astype(dtype)
        want = frames.transpose(0, 3, 1, 2).reshape(9, 35)
        for source in (frames, frames[:, :, ::-1][:, :, ::-1], torch.as_tensor(frames.astype(np.float32))):
            got = torch.stack(fused.frame_planes(source)).numpy()
            np.testing.assert_array_equal(got, want.astype(got.dtype))
    mono = rng.integers(0, 255, (2, 4, 6, 1), dtype=np.uint8)
    np.testing.assert_array_equal(torch.stack(fused.frame_planes(mono)).numpy(), mono[..., 0].reshape(2, 24))


def test_compiled_solver_equals_eager_solver(scene, device):
    """uint8 frames, uint8 observations and finite float observations take the compiled path
    and agree with the eager solver to float32 rounding; a NaN takes the eager path."""
    frames = scene.frames.astype(np.uint8)
    g = channel_groups(4)
    eager = FarFieldSolver(scene.lights_far(), groups=g, device=device)
    fast = FarFieldSolver(scene.lights_far(), groups=g, device=device, compile=True)
    ref = eager.solve_frames(frames)
    _assert_same(fast.solve_frames(frames), ref)
    if shutil.which("g++") or shutil.which("clang++"):
        assert fast.compile, "compilation failed on a machine with a C++ compiler"
    obs = scene.observations.astype(np.float32).round()
    _assert_same(fast.solve(obs.astype(np.uint8)), eager.solve(obs.astype(np.uint8)))
    _assert_same(fast.solve(obs), eager.solve(obs))
    obs[5, 1, 1] = np.nan
    got = fast.solve(obs)
    _assert_same(got, eager.solve(obs))
    assert np.isfinite(got.normals).all()


def test_compile_failure_falls_back_to_the_eager_solver(scene, monkeypatch):
    def broken():
        def run(*args):
            raise RuntimeError("no C++ compiler found")
        return run

    monkeypatch.setattr(fused, "compiled_farfield", broken)
    frames = scene.frames.astype(np.uint8)
    fast = FarFieldSolver(scene.lights_far(), groups=channel_groups(4), compile=True)
    with pytest.warns(RuntimeWarning, match="no C.. compiler found"):
        got = fast.solve_frames(frames)
    assert not fast.compile  # later frames go straight to the eager solver
    # The fallback is the eager solver on torch, the plain CPU solver runs on numpy: the same
    # arithmetic, equal to float32 rounding (summation order).
    _assert_same(got, FarFieldSolver(scene.lights_far(), groups=channel_groups(4)).solve_frames(frames), atol=1e-6)


def test_coloured_patterns_keep_the_alternating_solver(scene):
    """Per-channel albedo alternation is not in the kernel: such a solver never compiles."""
    L = scene.lights_far().copy()
    L[1::3] *= np.array([1.0, 0.5, 1.0])  # the green channel sees other lights
    assert not FarFieldSolver(L, groups=channel_groups(4), compile=True).compile


def test_huge_finite_observations_stay_finite(scene):
    """1e30 is finite but its square overflows float32: neither path may return Inf."""
    obs = scene.observations.astype(np.float32)
    obs[:, 4, 4] = 1e30
    for compile in (False, True):
        got = FarFieldSolver(scene.lights_far(), groups=channel_groups(4), compile=compile).solve(obs)
        for name in FIELDS:
            assert np.isfinite(getattr(got, name)).all(), (compile, name)
