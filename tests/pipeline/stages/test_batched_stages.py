"""The GPU path of ``reconstruct``/``batch`` (``--device cuda``): every contact instance as one
batch on the device (near-field normals, FFT depth), equal to the per-instance CPU stages to
float rounding. Run on the CPU here (the same torch code); CUDA against CPU where a GPU is present."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from support_recon import _one_torch_thread  # noqa: F401  (autouse)


@pytest.fixture(scope="module")
def capture_and_lights():
    from pipeline.solving.light_files import capture_lights
    from pipeline.stages.synthesize import illumination_record
    from sim.contacts import contact_surfaces
    from sim.render import bare_ring_illumination
    from sim.rendered_capture import render_capture

    model = bare_ring_illumination((40, 56), 0.2)
    cap = render_capture(model, "monochromatic", contact_surfaces("sphere", (40, 56), 0.2, 3, size_mm=2.0, seed=2),
                         noise_dn=1.0, bit_depth=8, seed=4)
    return cap, capture_lights(cap, None, illumination_record(model))


from pipeline.frame_pipeline.outputs import OutputSpec  # noqa: E402

ALL = OutputSpec.parse("all")  # every dataset, albedo and count included


def _compare(a, b):
    both = a.data["mask"] & b.data["mask"]
    assert (a.data["mask"] == b.data["mask"]).mean() > 0.999 and both.mean() > 0.5
    np.testing.assert_allclose(a.data["normals"][both], b.data["normals"][both], atol=3e-5)
    np.testing.assert_allclose(a.data["albedo"][both], b.data["albedo"][both], rtol=1e-3, atol=1e-3)


def test_batched_normals_and_device_depth_equal_the_stages(capture_and_lights):
    from pipeline.stages import depth, normals

    cap, lights = capture_and_lights
    eager = normals.compute(cap, lights, outputs=ALL, solver="nearfield", batched=False)
    batch = normals.compute(cap, lights, outputs=ALL, solver="nearfield", batched=True)
    assert batch.meta["method"] == "batched" and eager.meta.get("method") != "batched"
    _compare(batch, eager)
    d_ref = depth.compute(eager, "dst", region=None)
    scale = np.abs(d_ref.data["height"]).max()
    d_par = depth.compute(eager, "dst", region=None, threads=3)  # a run of instances per thread: FastDST
    assert d_par.meta["method"] == "fast"
    np.testing.assert_array_equal(d_par.data["mask"], d_ref.data["mask"])
    np.testing.assert_allclose(d_par.data["height"], d_ref.data["height"], atol=1e-5 * scale)
    d_seq = depth.compute(eager, "fc", region=None)
    np.testing.assert_array_equal(depth.compute(eager, "fc", region=None, threads=3).data["height"],
                                  d_seq.data["height"])  # the other integrators: instances in parallel, same heights
    d_dev = depth._compute_on_device(eager, float(eager.meta["mm_per_px"]), None, "cpu")
    np.testing.assert_array_equal(d_dev.data["mask"], d_ref.data["mask"])
    np.testing.assert_allclose(d_dev.data["height"], d_ref.data["height"], atol=2e-5 * scale)


def test_threads_take_the_batch_fast_path(capture_and_lights):
    """``--threads`` other than 1: nearfield on integer frames by NearFieldFast.solve_batch, every
    instance at once (equal to the eager solver to float32 rounding); float64 stays eager."""
    from pipeline.stages import normals

    cap, lights = capture_and_lights
    eager = normals.compute(cap, lights, outputs=ALL, solver="nearfield")
    fast = normals.compute(cap, lights, outputs=ALL, solver="nearfield", threads=2)
    assert fast.meta["method"] == "fast" and eager.meta.get("method") != "fast"
    assert fast.data["normals"].shape == eager.data["normals"].shape and fast.data["count"].dtype == np.int32
    _compare(fast, eager)
    assert normals.compute(cap, lights, outputs=ALL, solver="nearfield", threads=2, dtype="float64").meta.get("method") != "fast"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: the CUDA-vs-CPU check needs a GPU")
def test_reconstruct_on_cuda_equals_cpu(capture_and_lights, tmp_path):
    from pipeline.stages.synthesize import illumination_record
    from pipeline.workflows.reconstruct import reconstruct
    from sim.render import bare_ring_illumination

    cap, _ = capture_and_lights
    ill = illumination_record(bare_ring_illumination((40, 56), 0.2))
    cpu = reconstruct(cap, illumination=ill, solver="nearfield", store=tmp_path / "a", force=True)
    gpu = reconstruct(cap, illumination=ill, solver="nearfield", store=tmp_path / "b", force=True, device="cuda")
    assert gpu.normals.meta["method"] == "batched"
    _compare(gpu.normals, cpu.normals)
    scale = np.abs(cpu.depth.data["height"]).max()
    np.testing.assert_allclose(gpu.depth.data["height"], cpu.depth.data["height"], atol=1e-4 * scale)
