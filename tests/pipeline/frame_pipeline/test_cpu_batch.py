"""The CPU frame pipeline (:class:`pipeline.frame_pipeline.cpu_batch.CPUFramePipeline`): a stack of
frames solved and integrated on every thread gives each frame exactly what the per-frame fast path
gives."""

from __future__ import annotations

import numpy as np
import pytest

from support_recon import (
    _one_torch_thread,  # noqa: F401  (autouse: one torch thread)
    uint8_sphere_scene,
)


@pytest.mark.parametrize("coloured", [False, True])
def test_frames_in_parallel_equal_one_at_a_time(coloured):
    """CPUFramePipeline (the kernel over a stack, runs of pixels of every frame per thread, then
    runs of frames per thread for the depth) gives each frame exactly what the per-frame path
    gives; with a region (scattered in the kernel), a dark frame, 52 x 36 (a short last block)."""
    from pipeline.depth.fast import FastDST
    from pipeline.frame_pipeline.cpu_batch import CPUFramePipeline
    from pipeline.normals.fast import NearFieldFast

    frames, lights, _ = uint8_sphere_scene(coloured=coloured)
    P, H, W, C = frames.shape
    rng = np.random.default_rng(3)
    stack = np.clip(frames[None] + rng.integers(-3, 4, size=(5,) + frames.shape), 0, 255).astype(np.uint8)
    region = np.zeros((H, W), bool)
    region[2:, 4:-3] = True
    fast = NearFieldFast(lights.reshape(P * C, H, W, 3), groups=np.tile(np.arange(C), P), mask=region,
                         dark=np.full((H, W, C), 2.0, np.float32))
    dst = FastDST((H, W), 0.1)
    with CPUFramePipeline(fast, dst, threads=2) as pipe:
        out = pipe.run(stack)
    for k in range(len(stack)):
        one = fast.solve(stack[k])
        got = out["planes"].result(k)
        for name in ("normals", "albedo", "residual", "mask", "condition", "count"):
            np.testing.assert_array_equal(getattr(got, name), getattr(one, name), err_msg=name)
        ref = dst.integrate(one.normals, one.mask)
        np.testing.assert_array_equal(out["height"][k], ref.height)
        np.testing.assert_array_equal(out["height_mask"][k], ref.mask)
