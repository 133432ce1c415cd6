"""The fused CUDA near-field kernel and the GPU pipeline, on a machine without a GPU:

- it compiles to PTX with the real numba-cuda compiler (libNVVM, no driver);
- its logic under numba's CUDA simulator equals the torch solver's (NearFieldBatched on the CPU)
  to float32 rounding, with coloured lights (the per-channel albedo alternation), a dark frame
  and a flat field;
- ``iristac doctor --cpu-only`` reports the stack and exits 0 where numba-cuda and libNVVM are.

The GPU frame pipeline that runs the kernel (normals, then heights) is tested in
``tests/pipeline/frame_pipeline/test_gpu_stream.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from helpers import REPO


def _have_nvvm() -> tuple[bool, str]:
    from pipeline.cli.doctor import nvvm_status

    status, line = nvvm_status()
    return status == "ok", line


def test_nearfield_kernel_compiles_to_ptx():
    ok, why = _have_nvvm()
    if not ok:
        pytest.skip(why)
    from pipeline.depth.gpu_dst import compile_ptx as divergence_ptx
    from pipeline.normals.gpu_nearfield import compile_ptx

    for name, ptx in (("uint8", compile_ptx("uint8")), ("uint16", compile_ptx("uint16")),
                      ("divergence", divergence_ptx())):
        assert ".entry" in ptx, name
        assert ".f64" not in ptx, name  # float32 throughout: no double arithmetic


_SIM = r"""
import json, numpy as np
from numba import cuda
from pipeline.normals.gpu_nearfield import nearfield_kernel, THREADS
d = np.load(__import__("sys").argv[1])
frames, dark, invflat, L, Q, inv, valid0 = (d[k] for k in ("frames", "dark", "invflat", "L", "Q", "inv", "valid0"))
B, P, H, W, C = frames.shape
M = H * W
n, rho = np.zeros((B, 3, M), np.float32), np.zeros((B, C, M), np.float32)
res, ok = np.zeros((B, M), np.float32), np.zeros((B, M), np.uint8)
nearfield_kernel()[((M + THREADS - 1) // THREADS, B), (THREADS, 1)](frames, dark, invflat, True, True, L, Q, inv,
                                                                     valid0, int(d["iterations"]), n, rho, res, ok)
from numba import float32
from pipeline.depth.gpu_dst import divergence_kernel
ext, valid = np.zeros((B, 2 * H, 2 * W), np.float32), np.zeros((B, M), np.uint8)
divergence_kernel()[((M + THREADS - 1) // THREADS, B), (THREADS, 1)](n, ok, H, W, float32(0.1), float32(20.0), ext,
                                                                     valid)
print(json.dumps({"n": n.tolist(), "rho": rho.tolist(), "res": res.tolist(), "ok": ok.tolist(),
                  "ext": ext.tolist(), "valid": valid.tolist()}))
"""


def test_nearfield_kernel_logic_in_the_simulator(tmp_path):
    """Every output of the kernel (simulated, numpy in and out) against NearFieldBatched on the CPU."""
    from pipeline.normals.batched import NearFieldBatched

    rng = np.random.default_rng(1)
    P, C, H, W = 5, 3, 4, 6
    L = rng.normal(size=(P, C, H, W, 3)) * rng.uniform(0.7, 1.3, size=(1, C, 1, 1, 1))
    L[..., 2] = np.abs(L[..., 2]) + 1.0
    L[0, :, 0, 0] = 0.0  # a pixel with a missing light
    frames = rng.integers(20, 250, size=(2, P, H, W, C), dtype=np.uint8)
    dark = rng.uniform(0, 10, size=(H, W, C)).astype(np.float32)
    flat = rng.uniform(0.8, 1.2, size=(P, C, H, W))
    ref = NearFieldBatched(L, flat_field=flat)
    assert ref.iterations > 0  # coloured lights: the alternation runs
    want = ref.solve(frames, dark=dark)
    M = H * W
    f = np.float32
    arrays = {"frames": frames, "dark": dark.transpose(2, 0, 1).reshape(C, M), "invflat": ref.invflat.numpy().astype(f),
              "L": ref.L.numpy().astype(f), "Q": ref.Q.numpy().astype(f), "inv": ref.inv.numpy().astype(f),
              "valid0": ref.valid0.numpy().reshape(M).astype(np.uint8), "iterations": np.int64(ref.iterations)}
    path = tmp_path / "inputs.npz"
    np.savez(path, **arrays)
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", PYTHONPATH=str(REPO))
    p = subprocess.run([sys.executable, "-W", "ignore", "-c", _SIM, str(path)], capture_output=True, text=True,
                       env=env, timeout=300, cwd=str(REPO))
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    n = np.array(got["n"]).transpose(0, 2, 1).reshape(2, H, W, 3)
    ok = np.array(got["ok"]).reshape(2, H, W).astype(bool)
    np.testing.assert_array_equal(ok, want["mask"].numpy())
    np.testing.assert_allclose(n, want["normals"].numpy(), atol=2e-5)
    rho = np.array(got["rho"]).transpose(0, 2, 1).reshape(2, H, W, C)
    np.testing.assert_allclose(rho, want["albedo"].numpy(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.array(got["res"]).reshape(2, H, W), want["residual"].numpy(), rtol=1e-3, atol=1e-3)
    # the divergence kernel on the simulated normals: dst_divergence_torch's right-hand side, extended
    from pipeline.depth.batched import dst_divergence_torch

    f, valid = dst_divergence_torch(torch.as_tensor(n, dtype=torch.float32), torch.as_tensor(ok), 0.1)
    ext = torch.cat([f, -f.flip(-1)], dim=-1)
    ext = torch.cat([ext, -ext.flip(-2)], dim=-2)
    np.testing.assert_allclose(np.array(got["ext"]), ext.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(np.array(got["valid"]).reshape(2, H, W).astype(bool), valid.numpy())


def test_doctor_cpu_only_reports_the_stack():
    ok, why = _have_nvvm()
    if not ok:
        pytest.skip(why)
    path = os.pathsep.join([str(REPO)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])
    p = subprocess.run([sys.executable, "-m", "pipeline", "doctor", "--cpu-only", "--no-compile"],
                       capture_output=True, text=True, timeout=300, cwd=str(REPO), env=dict(os.environ, PYTHONPATH=path))
    lines = p.stdout.strip().splitlines()
    assert p.returncode == 0, p.stdout + p.stderr
    assert [ln.split()[0] for ln in lines] == ["ok"] * len(lines)
    assert any(ln.split()[1] == "numba-cuda" for ln in lines) and any("libNVVM" in ln for ln in lines)
