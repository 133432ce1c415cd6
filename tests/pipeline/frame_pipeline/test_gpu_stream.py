"""The GPU frame pipeline (:class:`pipeline.frame_pipeline.gpu_stream.GPUFramePipeline`), where a
CUDA device is present: its normals and heights equal the CPU's fast near-field solver and FastDST,
from numpy frames, pinned memory and HDF5 files read straight into its pinned buffers."""

from __future__ import annotations

import numpy as np
import pytest
import torch


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_gpu_pipeline_heights_equal_the_cpu():
    from pipeline.bench.recon_scene import render_sphere_scene
    from pipeline.depth.fast import FastDST
    from pipeline.frame_pipeline.gpu_stream import GPUFramePipeline
    from pipeline.normals.fast import NearFieldFast

    s = render_sphere_scene((48, 64), 0.1, radius=1.5, depth=0.4, num_patterns=8, noise=1.0, bits=8, seed=0)
    one = s.frames.astype(np.uint8)
    cpu = NearFieldFast(s.lights_flat(), groups=np.tile(np.arange(3), 8)).solve(one)
    h_cpu = FastDST((48, 64), 0.1).integrate(cpu.normals, cpu.mask).height
    frames = np.repeat(one[None], 7, axis=0)  # 7 frames in batches of 3: a short last batch
    for solver in ("fused", "torch"):
        pipe = GPUFramePipeline(s.lights, 0.1, batch=3, solver=solver)
        out = pipe.run(frames, normals=True)
        pinned = torch.full((7, 48, 64), float("nan")).pin_memory()
        pipe.run(torch.from_numpy(frames).pin_memory(), out=pinned)  # straight into pinned memory
        pipe.close()
        assert np.abs(out["normals"] - cpu.normals[None])[:, cpu.mask].max() < 1e-4, solver
        assert np.abs(out["height"] - h_cpu[None]).max() < 1e-4, solver
        assert np.abs(pinned.numpy() - h_cpu[None]).max() < 1e-4, solver


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_gpu_pipeline_reads_hdf5_frames_into_pinned_buffers(tmp_path):
    """Frames read from HDF5 straight into the pipeline's pinned buffers (by offsets from an
    unfiltered file, through the filters from a compressed one) give the heights the same
    frames give from numpy."""
    import h5py

    from pipeline.base.h5frames import H5Frames
    from pipeline.bench.recon_scene import render_sphere_scene
    from pipeline.frame_pipeline.gpu_stream import GPUFramePipeline

    s = render_sphere_scene((48, 64), 0.1, radius=1.5, depth=0.4, num_patterns=8, noise=1.0, bits=8, seed=0)
    rng = np.random.default_rng(0)
    frames = np.clip(s.frames[None] + rng.integers(-2, 3, size=(7,) + s.frames.shape), 0, 255).astype(np.uint8)
    for name, kw in (("plain", {}), ("lzf", {"chunks": (1, 1, 48, 64, 3), "compression": "lzf"})):
        with h5py.File(tmp_path / f"{name}.h5", "w") as f:
            f.create_dataset("frames", data=frames, **kw)
    pipe = GPUFramePipeline(s.lights, 0.1, batch=3)
    want = pipe.run(frames)["height"]
    for name, direct in (("plain", True), ("lzf", False)):
        with H5Frames(tmp_path / f"{name}.h5") as src:
            assert src.direct is direct
            pinned = torch.full((7, 48, 64), float("nan")).pin_memory()
            pipe.run(src, out=pinned)
        np.testing.assert_allclose(pinned.numpy(), want, rtol=0, atol=1e-6)
    pipe.close()
