"""DST Poisson heights of a batch of normal planes on a CUDA device: one kernel, then the batched FFT.

:func:`pipeline.depth.batched.dst_divergence_torch` builds the Poisson right-hand side from
normals in about twenty elementwise torch operations (each a pass over the batch), and
:func:`~pipeline.depth.batched.dst_heights` copies it twice more into its antisymmetric
``(2H, 2W)`` extension. Here one thread per pixel computes the slopes of the pixel and its four
neighbours from the normal planes (the same clamping and masks, in the same float32 order), the
divergence ``f``, and writes ``f`` straight into the four quadrants of the extension; the
heights are then ``irfft2(rfft2(ext) / lambda)`` cropped (cuFFT, batched), as ``dst_heights``.
Equal to those two functions to float32 rounding (``tests/pipeline/normals/test_gpu_nearfield.py``
runs the kernel in numba's CUDA simulator).
"""

from __future__ import annotations

import functools
import math

from numba import cuda, float32

__all__ = ["GPUDST", "compile_ptx", "divergence_kernel", "kernel_signature"]

THREADS = 128


def _slopes(n, mask, b, m, scale_mm, max_slope):  # pragma: no cover - compiled (device)
    """``(gc, gr, valid)`` at pixel ``m`` of frame ``b``: the column and row height steps (mm)."""
    nx = n[b, 0, m]
    ny = n[b, 1, m]
    nz = n[b, 2, m]
    valid = (mask[b, m] != 0) and (nz > 0) and math.isfinite(nz)
    safe = nz if valid else float32(1.0)
    p = -nx / safe if valid else float32(0.0)
    q = -ny / safe if valid else float32(0.0)
    ok = math.isfinite(p) and math.isfinite(q)
    valid = valid and ok
    p = p if ok else float32(0.0)
    q = q if ok else float32(0.0)
    mag = math.hypot(p, q)
    s = max_slope / max(mag, float32(1.1754944e-38)) if mag > max_slope else float32(1.0)
    return p * s * scale_mm, -(q * s) * scale_mm, valid


def _kernel(n, mask, H, W, scale_mm, max_slope, ext, valid_out):  # pragma: no cover - compiled
    """``n (B, 3, H*W)`` float32 planes, ``mask (B, H*W)`` uint8 -> ``ext (B, 2H, 2W)`` (the antisymmetric
    extension of the divergence) and ``valid_out (B, H*W)`` uint8."""
    m, b = cuda.grid(2)
    if m >= H * W or b >= n.shape[0]:
        return
    i = m // W
    j = m - i * W
    half = float32(0.5)
    gc, gr, ok = _slopes(n, mask, b, m, scale_mm, max_slope)
    # column edges: j (left) and j + 1 (right); the border edges carry the border pixel's step
    if j > 0:
        left, _, _ = _slopes(n, mask, b, m - 1, scale_mm, max_slope)
        e0 = half * (gc + left)
    else:
        e0 = gc
    if j < W - 1:
        right, _, _ = _slopes(n, mask, b, m + 1, scale_mm, max_slope)
        e1 = half * (right + gc)
    else:
        e1 = gc
    if i > 0:
        _, up, _ = _slopes(n, mask, b, m - W, scale_mm, max_slope)
        r0 = half * (gr + up)
    else:
        r0 = gr
    if i < H - 1:
        _, down, _ = _slopes(n, mask, b, m + W, scale_mm, max_slope)
        r1 = half * (down + gr)
    else:
        r1 = gr
    f = (e1 - e0) + (r1 - r0)
    ext[b, i, j] = f
    ext[b, i, 2 * W - 1 - j] = -f
    ext[b, 2 * H - 1 - i, j] = -f
    ext[b, 2 * H - 1 - i, 2 * W - 1 - j] = f
    valid_out[b, m] = 1 if ok else 0


def kernel_function():
    """The kernel's Python function with ``_slopes`` bound to its CUDA device version (inlined at
    numba's IR level, so it compiles to PTX without a driver)."""
    import types

    ns = dict(_kernel.__globals__)
    ns["_slopes"] = cuda.jit(device=True, inline="always")(_slopes)
    return types.FunctionType(_kernel.__code__, ns, _kernel.__name__, _kernel.__defaults__, _kernel.__closure__)


@functools.cache
def divergence_kernel():
    return cuda.jit(kernel_function())


def kernel_signature():
    from numba import types as nt

    f4 = nt.float32
    return (f4[:, :, ::1], nt.uint8[:, ::1], nt.int64, nt.int64, f4, f4, f4[:, :, ::1], nt.uint8[:, ::1])


def compile_ptx(cc=(9, 0)) -> str:
    """PTX of the divergence kernel (numba-cuda's compiler, libNVVM; no GPU needed)."""
    ptx, _ = cuda.compile_ptx(kernel_function(), kernel_signature(), cc=cc)
    return ptx


class GPUDST:
    """Heights ``(B, H, W)`` of normal planes ``(B, 3, H*W)`` on torch's current CUDA stream.

    Parameters
    ----------
    shape : (H, W)
    mm_per_px, max_slope : float
        As :class:`pipeline.depth.fast.FastDST`.
    device : torch device
    """

    def __init__(self, shape, mm_per_px: float, max_slope: float = 20.0, device="cuda"):
        import torch

        self.shape = (int(shape[0]), int(shape[1]))
        self.mm, self.max_slope = float(mm_per_px), float(max_slope)
        self.device = torch.device(device)
        H, W = self.shape
        ky = 2.0 * torch.cos(torch.pi * torch.arange(2 * H, dtype=torch.float64) / H) - 2.0
        kx = 2.0 * torch.cos(torch.pi * torch.arange(W + 1, dtype=torch.float64) / W) - 2.0
        lam = ky[:, None] + kx[None, :]
        lam[0, 0] = 1.0
        inv = 1.0 / lam
        inv[0, 0] = 0.0  # the extension's mean is 0: drop the constant
        self.inv_eig = inv.to(device=self.device, dtype=torch.float32)

    def heights(self, planes, mask):
        """``(height (B, H, W), valid (B, H, W) bool)`` of float32 normal planes ``(B, 3, H*W)`` and a
        uint8 ``mask (B, H*W)`` (both contiguous device tensors)."""
        import torch

        B = planes.shape[0]
        H, W = self.shape
        ext = torch.empty((B, 2 * H, 2 * W), device=planes.device, dtype=torch.float32)
        valid = torch.empty((B, H * W), device=planes.device, dtype=torch.uint8)

        def a(x):
            return cuda.as_cuda_array(x, sync=False)

        stream = cuda.external_stream(torch.cuda.current_stream(planes.device).cuda_stream)
        divergence_kernel()[((H * W + THREADS - 1) // THREADS, B), (THREADS, 1), stream](
            a(planes), a(mask), H, W, float32(self.mm), float32(self.max_slope), a(ext), a(valid))
        F = torch.fft.rfft2(ext)
        F.mul_(self.inv_eig)
        h = torch.fft.irfft2(F, s=(2 * H, 2 * W))[:, :H, :W]
        return h, valid.reshape(B, H, W).bool()
