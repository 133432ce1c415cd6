"""The live fast paths agree with their eager references to float rounding.

- near field: :class:`pipeline.normals.fast.NearFieldFast` (Numba) and
  :class:`pipeline.normals.batched.NearFieldBatched` (torch, any device) against
  :class:`pipeline.normals.nearfield.NearFieldSolver` in float64; white sectors (channels
  sharing their lights: the compressed layout) and coloured lights (per-channel albedo
  alternation), with a mask, a dark frame and a flat field;
- depth: :class:`pipeline.depth.fast.FastDST` and :func:`pipeline.depth.batched.dst_heights`
  against :func:`pipeline.depth.poisson.poisson_dst`;
- the calibration's LUT and MLP: :class:`pipeline.normals.fast_models.FastLUT` /
  ``FastMLP`` against the models' own ``normal_maps``;
- CUDA against CPU where a GPU is present (skipped otherwise).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from support_recon import _one_torch_thread  # noqa: F401  (autouse: one torch thread)
from support_recon import uint8_sphere_scene as _uint8_scene


@pytest.mark.parametrize("coloured,masked", [(False, True), (False, False), (True, True)])
def test_nearfield_fast_equals_eager(coloured, masked):
    from pipeline.normals.fast import NearFieldFast
    from pipeline.normals.nearfield import NearFieldSolver

    frames, lights, _ = _uint8_scene(coloured=coloured)
    P, H, W, C = frames.shape
    L = lights.reshape(P * C, H, W, 3)
    groups = np.tile(np.arange(C), P)
    region = np.zeros((H, W), bool)
    region[3:-2, 5:] = True
    if not masked:  # every pixel: white sectors read the interleaved frames directly
        region[:] = True
    dark = np.full((H, W, C), 2.0, np.float32)
    flat = np.random.default_rng(1).uniform(0.8, 1.2, size=(P * C, H, W))
    fast = NearFieldFast(L, groups=groups, mask=region if masked else None, dark=dark, flat_field=flat)
    assert fast.shared is (not coloured) and (fast.iterations > 0) is coloured
    got = fast.solve(frames, threads=2)
    obs = (frames.astype(np.float64) - dark).transpose(0, 3, 1, 2).reshape(P * C, H, W) / flat
    ref = NearFieldSolver(L, groups=groups, dtype="float64", mask=region).solve(obs)
    both = got.mask & ref.mask
    assert (got.mask == ref.mask).mean() > 0.999 and both.sum() > 0.6 * region.sum()
    assert not got.mask[~region].any()
    np.testing.assert_allclose(got.normals[both], ref.normals[both], atol=2e-5)
    np.testing.assert_allclose(got.albedo[both], ref.albedo[both], rtol=2e-4, atol=1e-4)
    np.testing.assert_allclose(got.residual[both], ref.residual[both], atol=2e-2 * ref.residual[both].max())
    np.testing.assert_array_equal(got.normals[~got.mask], np.tile([0, 0, 1], ((~got.mask).sum(), 1)))


def test_lstsq_fast_equals_eager():
    """``lstsq``'s fast path (the far-field vectors at every pixel through the near-field kernel)
    against its eager solve path, both from the registry through ``frame_solver``."""
    from pipeline.normals.lights import LightSource
    from pipeline.solving.frame_solvers import frame_solver

    frames, lights, _ = _uint8_scene()
    P, H, W, C = frames.shape
    src = LightSource(field=lights, source="test")  # far field: the light field at the image centre
    fast, eager = (frame_solver("lstsq", src, shape=(H, W), fast=f) for f in (True, False))
    assert (fast.method, eager.method) == ("fast", "eager")
    a, b = fast.solve(frames), eager.solve(frames)
    both = a.mask & b.mask
    assert (a.mask == b.mask).mean() > 0.999 and both.mean() > 0.5
    np.testing.assert_allclose(a.normals[both], b.normals[both], atol=1e-4)


def test_nearfield_batched_equals_fast(device):
    from pipeline.normals.batched import NearFieldBatched
    from pipeline.normals.fast import NearFieldFast

    frames, lights, _ = _uint8_scene(coloured=True)
    P, H, W, C = frames.shape
    batch = np.stack([frames, np.roll(frames, 3, axis=2)])
    fast = NearFieldFast(lights.reshape(P * C, H, W, 3), groups=np.tile(np.arange(C), P))
    dev = NearFieldBatched(lights, device=device)
    out = {k: v.cpu().numpy() for k, v in dev.solve(batch).items()}
    for b in range(2):
        ref = fast.solve(batch[b])
        both = ref.mask & out["mask"][b]
        assert (ref.mask == out["mask"][b]).mean() > 0.999
        np.testing.assert_allclose(out["normals"][b][both], ref.normals[both], atol=3e-5)
        np.testing.assert_allclose(out["albedo"][b][both], ref.albedo[both], rtol=5e-4, atol=1e-4)


def test_fast_dst_equals_poisson_dst(device):
    from pipeline.depth.batched import dst_divergence_torch, dst_heights
    from pipeline.depth.fast import FastDST
    from pipeline.depth.poisson import poisson_dst

    _, _, scene = _uint8_scene(shape=(40, 56))
    n = scene.normals.astype(np.float32)
    mask = np.ones(n.shape[:2], bool)
    mask[5:9, 7:20] = False
    n[20, 30] = [0.999, 0.0, 0.01]  # a grazing normal: clipped to max_slope
    ref = poisson_dst(n, 0.1, mask)
    got = FastDST(n.shape[:2], 0.1).integrate(n, mask)
    np.testing.assert_array_equal(got.mask, ref.mask)
    scale = np.abs(ref.height).max()
    np.testing.assert_allclose(got.height, ref.height, atol=1e-5 * scale + 1e-7)
    f, valid = dst_divergence_torch(torch.as_tensor(n, device=device)[None], torch.as_tensor(mask, device=device)[None],
                                    0.1)
    h = dst_heights(f)[0].cpu().numpy()
    np.testing.assert_array_equal(valid[0].cpu().numpy(), ref.mask)
    np.testing.assert_allclose(h, ref.height, atol=2e-5 * scale + 1e-7)
    # float64 in, float64 out: the FFT form is the DST form to double rounding.
    f64, _ = dst_divergence_torch(torch.as_tensor(n, dtype=torch.float64)[None], torch.as_tensor(mask)[None], 0.1)
    ref64 = poisson_dst(n.astype(np.float64), 0.1, mask).height
    np.testing.assert_allclose(dst_heights(f64)[0].numpy(), ref64, atol=1e-6 * scale)


@pytest.fixture(scope="module")
def real_models():
    """A LUT and an MLP calibrated on a few shared real presses (short MLP schedule)."""
    from helpers import SHARED

    data = SHARED / "data" / "gelsight_ball_presses.npz"
    if not data.is_file():
        pytest.skip(f"shared real frames not found at {data}")
    from calibration.calibrate import calibrate
    from calibration.importers import load_gelsight_npz
    from pipeline.base.threads import limit_threads

    cap = load_gelsight_npz(data)
    with limit_threads(torch=1):
        res = calibrate(cap.select(slice(0, 6)), 2.0, cap.mm_per_px, ["lut", "mlp"], folds=2, refine_iterations=0,
                        model_options={"mlp": {"epochs": 40, "max_samples": 1000, "members": 2}})
        # The position as a degree-2 polynomial (u, v, u^2, uv, v^2): the first layer's fixed part.
        quad = calibrate(cap.select(slice(0, 6)), 2.0, cap.mm_per_px, ["mlp"], folds=2, refine_iterations=0,
                         model_options={"mlp": {"epochs": 20, "max_samples": 500, "position_degree": 2}})
    return {**res.models, "mlp-degree2": quad.models["mlp"]}, cap


@pytest.mark.parametrize("case", ["lut", "mlp", "mlp-degree2"])
def test_model_fast_paths_equal_normal_maps(real_models, case):
    """Drift removal off: the fast path is the model's ``normal_maps`` of the frames. On (the
    default for these solvers; the frames drifted by up to 15 % gain and 30 DN): it fits the same
    drift from the same pixels as the eager path, and both equal ``normal_maps`` of the frames
    with that drift removed."""
    from pipeline.normals.drift import drifted_capture
    from pipeline.normals.lights import LightSource
    from pipeline.solving.frame_solvers import frame_solver

    all_models, cap = real_models
    name = case.split("-")[0]
    models = {name: all_models[case]}
    models[name].tilt_gain = 1.07  # the output correction goes through the fast path too
    models[name].max_tilt = 0.9
    frames, ref = cap.linear()
    src = LightSource(models=models, source="test")
    fs = frame_solver(name, src, shape=frames.shape[2:4], reference=ref, drift="none")
    assert fs.method == "fast"
    atol = 1e-5 if name == "mlp" else 1e-7
    for k in (21, 27):
        got = fs.solve(np.asarray(cap.frames[k]), threads=2)
        maps = models[name].normal_maps(frames[k:k + 1], ref)
        np.testing.assert_array_equal(got.mask, maps.mask[0])
        np.testing.assert_allclose(got.normals, maps.normals[0], atol=atol)
        np.testing.assert_allclose(got.confidence, maps.confidence[0], atol=1e-5)
        assert got.mask.mean() > 0.5 and "drift" not in got.meta
    drifted = drifted_capture(cap.select([21, 27]), seed=3)
    fast, eager = (frame_solver(name, src, shape=frames.shape[2:4], reference=ref, fast=f) for f in (True, False))
    assert (fast.method, eager.method) == ("fast", "eager")
    assert fast.drift.model == eager.prep.drift_model == "gain_offset"
    for k in range(2):
        raw = np.asarray(drifted.frames[k])
        fast.reset_drift()  # live refits every few frames: fit this one
        eager.reset_drift()
        got, want = fast.solve(raw, threads=2), eager.solve(raw)
        assert got.meta["drift"] == want.meta["drift"] == "gain_offset"
        assert got.meta["drift_before_dn"] == want.meta["drift_before_dn"] > 10
        d = eager.prep.drifts[0]
        maps = models[name].normal_maps(d.remove(raw.astype(np.float32))[None], ref)
        for res in (got, want):
            np.testing.assert_array_equal(res.mask, maps.mask[0])
            np.testing.assert_allclose(res.normals, maps.normals[0], atol=atol)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: the CUDA-vs-CPU check needs a GPU")
def test_batched_cuda_equals_cpu():
    from pipeline.depth.batched import dst_divergence_torch, dst_heights
    from pipeline.normals.batched import NearFieldBatched

    frames, lights, scene = _uint8_scene(shape=(48, 64), coloured=True)
    batch = np.stack([frames] * 4)
    outs = {}
    for dev in ("cpu", "cuda"):
        r = NearFieldBatched(lights, device=dev).solve(batch)
        f, valid = dst_divergence_torch(r["normals"], r["mask"], scene.mm_per_px)
        outs[dev] = (r["normals"].cpu().numpy(), r["mask"].cpu().numpy(), dst_heights(f).cpu().numpy())
    both = outs["cpu"][1] & outs["cuda"][1]
    assert (outs["cpu"][1] == outs["cuda"][1]).mean() > 0.999
    np.testing.assert_allclose(outs["cuda"][0][both], outs["cpu"][0][both], atol=1e-5)
    np.testing.assert_allclose(outs["cuda"][2], outs["cpu"][2], atol=1e-5 * np.abs(outs["cpu"][2]).max())
