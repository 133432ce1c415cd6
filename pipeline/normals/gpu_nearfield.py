"""Near-field normals of a batch of integer frames in one fused CUDA kernel (``numba.cuda``).

:class:`pipeline.normals.batched.NearFieldBatched` solves a batch with a chain of torch
einsums over float32 intermediates: every step reads and writes the whole batch again. Here one
thread owns one pixel of one frame and does the whole per-pixel solve in registers, reading
the frame's ``P x C`` integer observations once, straight from the uploaded uint8/uint16
batch: the moments ``r_c = sum_p I_pc L_pc`` and ``S_c = sum_p I_pc^2``, ``b = A^-1 sum_c r_c``,
the per-channel albedo alternation when the channels see different lights, the final albedo,
residual and mask. The factors (``L``, ``Q_c``, ``A^-1``, the validity) are
:class:`~pipeline.normals.batched.NearFieldBatched`'s, shared on the device, so the results
are that solver's to float32 rounding (``tests/pipeline/normals/test_gpu_nearfield.py``, in
numba's CUDA simulator on a CPU; ``tools/gpu_check.sh`` on a GPU).

Outputs are pixel-planar ``(B, 3, M)``, ``(B, C, M)``, ``(B, M)`` (coalesced writes) and
:meth:`NearFieldGPU.solve` returns torch views ``(B, H, W, 3)`` etc. of them, so depth
(:func:`pipeline.depth.batched.dst_divergence_torch`, :func:`~pipeline.depth.batched.dst_heights`)
follows on the same stream. :mod:`pipeline.frame_pipeline.gpu_stream` overlaps the uploads with this.

The kernel compiles in about a second on first use (in memory); :func:`compile_ptx` builds it
to PTX with no GPU (CI does).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import cuda, float32

__all__ = ["MAX_CHANNELS", "NearFieldGPU", "compile_ptx", "kernel_signature", "nearfield_kernel"]

#: Channels (albedo groups) a pixel's registers hold.
MAX_CHANNELS = 4
_TINY = np.float32(1.1754944e-38)
THREADS = 128


def _solve3(a00, a01, a02, a11, a12, a22, y0, y1, y2):  # pragma: no cover - compiled (device)
    """``A^-1 y`` for a symmetric ``A`` by the adjugate; 0 for a singular one (as ``batched._solve3``)."""
    c00 = a11 * a22 - a12 * a12
    c01 = a12 * a02 - a01 * a22
    c02 = a01 * a12 - a11 * a02
    det = a00 * c00 + a01 * c01 + a02 * c02
    idet = float32(1.0) / det if det != 0 else det - det
    x0 = c00 * y0 + c01 * y1 + c02 * y2
    x1 = c01 * y0 + (a00 * a22 - a02 * a02) * y1 + (a02 * a01 - a00 * a12) * y2
    x2 = c02 * y0 + (a01 * a02 - a00 * a12) * y1 + (a00 * a11 - a01 * a01) * y2
    return x0 * idet, x1 * idet, x2 * idet


def _quad(Q, c, m, n0, n1, n2):  # pragma: no cover - compiled (device)
    """``n^T Q_c n`` at pixel ``m``."""
    return (n0 * (Q[c, 0, 0, m] * n0 + Q[c, 0, 1, m] * n1 + Q[c, 0, 2, m] * n2)
            + n1 * (Q[c, 1, 0, m] * n0 + Q[c, 1, 1, m] * n1 + Q[c, 1, 2, m] * n2)
            + n2 * (Q[c, 2, 0, m] * n0 + Q[c, 2, 1, m] * n1 + Q[c, 2, 2, m] * n2))


def _kernel(frames, dark, invflat, use_dark, use_flat, L, Q, inv, valid0, iterations, normals, albedo, residual,
            mask):  # pragma: no cover
    """One thread per (pixel, frame): ``frames (B, P, H, W, C)`` integer; ``dark (C, M)`` and
    ``invflat (P, C, M)`` float32 (read where ``use_dark``, ``use_flat``); factors as NearFieldBatched's
    (``L (P, C, 3, M)``, ``Q (C, 3, 3, M)``, ``inv (3, 3, M)``, ``valid0 (M,)`` uint8); outputs
    ``normals (B, 3, M)``, ``albedo (B, C, M)``, ``residual (B, M)``, ``mask (B, M)`` uint8."""
    m, b = cuda.grid(2)
    B, P, H, W, C = frames.shape
    M = H * W
    if m >= M or b >= B:
        return
    row = m // W
    col = m - row * W
    tiny = float32(1.1754944e-38)
    r = cuda.local.array((MAX_CHANNELS, 3), float32)
    rho = cuda.local.array(MAX_CHANNELS, float32)
    S = float32(0.0)
    for c in range(C):
        r[c, 0] = r[c, 1] = r[c, 2] = float32(0.0)
    for p in range(P):
        for c in range(C):
            x = float32(frames[b, p, row, col, c])
            if use_dark:
                x -= dark[c, m]
            if use_flat:
                x *= invflat[p, c, m]
            r[c, 0] += x * L[p, c, 0, m]
            r[c, 1] += x * L[p, c, 1, m]
            r[c, 2] += x * L[p, c, 2, m]
            S += x * x
    y0 = y1 = y2 = float32(0.0)
    for c in range(C):
        y0 += r[c, 0]
        y1 += r[c, 1]
        y2 += r[c, 2]
    b0 = inv[0, 0, m] * y0 + inv[0, 1, m] * y1 + inv[0, 2, m] * y2
    b1 = inv[1, 0, m] * y0 + inv[1, 1, m] * y1 + inv[1, 2, m] * y2
    b2 = inv[2, 0, m] * y0 + inv[2, 1, m] * y1 + inv[2, 2, m] * y2
    for _ in range(iterations if C > 1 else 0):
        nn = max(math.sqrt(b0 * b0 + b1 * b1 + b2 * b2), tiny)
        n0, n1, n2 = b0 / nn, b1 / nn, b2 / nn
        mean = float32(0.0)
        for c in range(C):
            q = max(_quad(Q, c, m, n0, n1, n2), tiny)
            rho[c] = (r[c, 0] * n0 + r[c, 1] * n1 + r[c, 2] * n2) / q
            mean += rho[c]
        mean = mean / float32(C)
        a00 = a01 = a02 = a11 = a12 = a22 = y0 = y1 = y2 = float32(0.0)
        for c in range(C):
            rel = rho[c] / mean if (rho[c] > 0) and (mean > 0) else float32(1.0)
            w = rel * rel
            a00 += w * Q[c, 0, 0, m]
            a01 += w * Q[c, 0, 1, m]
            a02 += w * Q[c, 0, 2, m]
            a11 += w * Q[c, 1, 1, m]
            a12 += w * Q[c, 1, 2, m]
            a22 += w * Q[c, 2, 2, m]
            y0 += rel * r[c, 0]
            y1 += rel * r[c, 1]
            y2 += rel * r[c, 2]
        b0, b1, b2 = _solve3(a00, a01, a02, a11, a12, a22, y0, y1, y2)
    norm = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    nn = max(norm, tiny)
    n0, n1, n2 = b0 / nn, b1 / nn, b2 / nn
    ok = (valid0[m] != 0) and (norm > 0) and (n2 > 0)
    if not ok:
        n0 = n1 = float32(0.0)
        n2 = float32(1.0)
    fit = float32(0.0)
    for c in range(C):
        p_ = r[c, 0] * n0 + r[c, 1] * n1 + r[c, 2] * n2
        q = max(_quad(Q, c, m, n0, n1, n2), tiny)
        albedo[b, c, m] = p_ / q if ok else float32(0.0)
        fit += p_ * p_ / q
    normals[b, 0, m] = n0
    normals[b, 1, m] = n1
    normals[b, 2, m] = n2
    residual[b, m] = math.sqrt(max(S - fit, float32(0.0)) / float32(P * C)) if ok else float32(0.0)
    mask[b, m] = 1 if ok else 0


@functools.cache
def _device_functions():
    return {"_solve3": cuda.jit(device=True, inline="always")(_solve3),
            "_quad": cuda.jit(device=True, inline="always")(_quad)}


def _with_device_functions(fn):
    import types

    ns = dict(fn.__globals__)
    ns.update(_device_functions())
    return types.FunctionType(fn.__code__, ns, fn.__name__, fn.__defaults__, fn.__closure__)


def kernel_function():
    """The kernel's Python function, its helpers bound to their CUDA device versions (inlined at
    numba's IR level: it compiles as one function, so to PTX without a driver)."""
    return _with_device_functions(_kernel)


@functools.cache
def nearfield_kernel():
    """The compiled (lazily, per signature) CUDA kernel."""
    return cuda.jit(kernel_function())


def kernel_signature(frame_dtype="uint8"):
    """Numba signature of the kernel for frames of ``frame_dtype``."""
    from numba import types as nt

    fr = {"uint8": nt.uint8, "uint16": nt.uint16}[np.dtype(frame_dtype).name]
    f4 = nt.float32
    return (fr[:, :, :, :, ::1], f4[:, ::1], f4[:, :, ::1], nt.boolean, nt.boolean, f4[:, :, :, ::1], f4[:, :, :, ::1], f4[:, :, ::1],
            nt.uint8[::1], nt.int64, f4[:, :, ::1], f4[:, :, ::1], f4[:, ::1], nt.uint8[:, ::1])


def compile_ptx(frame_dtype="uint8", cc=(9, 0)) -> str:
    """PTX of the kernel (numba-cuda's compiler, libNVVM; no GPU needed)."""
    ptx, _ = cuda.compile_ptx(kernel_function(), kernel_signature(frame_dtype), cc=cc)
    return ptx


class NearFieldGPU:
    """The fused near-field solve on a CUDA device, with :class:`NearFieldBatched`'s factors.

    Parameters
    ----------
    lights : ndarray (P, C, H, W, 3)
    flat_field, max_condition, albedo_iterations :
        As :class:`pipeline.normals.batched.NearFieldBatched`.
    dark : ndarray (H, W, C), optional
        Subtracted from every frame.
    device : str
        ``cuda`` or ``cuda:N``.
    """

    def __init__(self, lights, *, flat_field=None, max_condition: float = 1e3, albedo_iterations: int | None = None,
                 dark=None, device="cuda"):
        import torch

        from pipeline.normals.batched import NearFieldBatched

        ref = NearFieldBatched(lights, flat_field=flat_field, max_condition=max_condition,
                               albedo_iterations=albedo_iterations, device=device)
        if ref.C > MAX_CHANNELS:
            raise ValueError(f"NearFieldGPU: at most {MAX_CHANNELS} channels, got {ref.C}")
        self.P, self.C, self.shape, self.device = ref.P, ref.C, ref.shape, ref.device
        self.iterations = int(ref.iterations)
        self.condition = ref.condition
        H, W = self.shape
        M = H * W
        t = dict(device=self.device, dtype=torch.float32)
        self.L = ref.L.contiguous()  # (P, C, 3, M)
        self.Q = ref.Q.contiguous()  # (C, 3, 3, M)
        self.inv = ref.inv.contiguous()  # (3, 3, M)
        self.valid0 = ref.valid0.reshape(M).to(torch.uint8).contiguous()
        # absent dark / flat field: 1-element stand-ins the kernel never reads (use_* False)
        self.invflat = ref.invflat.contiguous() if ref.invflat is not None else torch.zeros((1, 1, 1), **t)
        self.use_flat = ref.invflat is not None
        self.use_dark = dark is not None
        if dark is None:
            self.dark = torch.zeros((1, 1), **t)
        else:
            d = torch.as_tensor(np.asarray(dark, np.float32), **t)
            if tuple(d.shape) != (H, W, self.C):
                raise ValueError(f"NearFieldGPU: dark must be (H, W, C) = {(H, W, self.C)}, got {tuple(d.shape)}")
            self.dark = d.permute(2, 0, 1).reshape(self.C, M).contiguous()

    def solve(self, frames) -> dict:
        """Normals of a batch ``frames (B, P, H, W, C)`` uint8/uint16 torch tensor on the device, on
        torch's current stream. Returns torch tensors ``normals (B, H, W, 3)``, ``albedo (B, H, W, C)``
        (views of pixel-planar buffers), ``residual (B, H, W)``, ``mask (B, H, W)`` bool."""
        n, rho, res, ok = self.solve_planes(frames)
        B = n.shape[0]
        H, W = self.shape
        return {"normals": n.permute(0, 2, 1).reshape(B, H, W, 3),
                "albedo": rho.permute(0, 2, 1).reshape(B, H, W, self.C), "residual": res.reshape(B, H, W),
                "mask": ok.reshape(B, H, W).bool()}

    def solve_planes(self, frames):
        """The kernel's own outputs: ``normals (B, 3, M)``, ``albedo (B, C, M)``, ``residual (B, M)``
        float32 and ``mask (B, M)`` uint8 (``M = H * W``), device tensors."""
        import torch

        want = (self.P,) + self.shape + (self.C,)
        if tuple(frames.shape[1:]) != want or frames.dtype not in (torch.uint8, torch.uint16):
            raise ValueError(f"NearFieldGPU.solve: frames must be uint8/uint16 (B, {self.P}, {self.shape[0]}, "
                             f"{self.shape[1]}, {self.C}), got {frames.dtype} {tuple(frames.shape)}")
        B = frames.shape[0]
        H, W = self.shape
        M = H * W
        t = dict(device=frames.device, dtype=torch.float32)
        n = torch.empty((B, 3, M), **t)
        rho = torch.empty((B, self.C, M), **t)
        res = torch.empty((B, M), **t)
        ok = torch.empty((B, M), device=frames.device, dtype=torch.uint8)
        stream = cuda.external_stream(torch.cuda.current_stream(frames.device).cuda_stream)

        def a(x):  # the kernel runs on this stream: no host synchronisation on import
            return cuda.as_cuda_array(x, sync=False)

        grid = ((M + THREADS - 1) // THREADS, B)
        nearfield_kernel()[grid, (THREADS, 1), stream](
            a(frames.contiguous()), a(self.dark), a(self.invflat), self.use_dark, self.use_flat, a(self.L), a(self.Q),
            a(self.inv), a(self.valid0), self.iterations, a(n), a(rho), a(res), a(ok))
        return n, rho, res, ok
