"""The compiled ray kernel on a CUDA GPU (``numba.cuda``): one thread per ray, the CPU kernel's code.

The per-ray functions of :mod:`sim.optics.kernel` are plain ``@njit`` functions, which
``numba.cuda`` compiles as device functions: a GPU thread emits its ray
(:func:`sim.optics.kernel.emit`), traces it with :func:`sim.optics.kernel.trace_ray` (the
scalar path with the full Newton loops and bounces: a GPU has no SIMD lanes to fill) and adds
it to the images with atomic adds (one image set for the whole device; many threads per
pixel make atomics the GPU's way). Each thread keeps its energy books in registers over a
grid-stride loop and adds them once at the end.

Tested on CPU with numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``,
``tests/sim/test_tracer_kernel.py``); the real-GPU test runs where ``numba.cuda`` finds a device.
"""

from __future__ import annotations

import numpy as np
from numba import cuda

from sim.optics import kernel as K

__all__ = ["cuda_available", "trace", "warm_up"]

THREADS_PER_BLOCK = 256


def _device_functions_without_fastmath() -> None:
    """Give every ``@njit`` function of :mod:`sim.optics.kernel` its CUDA device dispatcher now, without
    fastmath: ``numba.cuda`` would otherwise copy the CPU options, and its fastmath is all or
    nothing (no-NaN, no-inf), which would let the compiler drop the kernel's ``inf`` tests. This
    fills the cache ``numba.cuda`` itself keeps on the CPU dispatcher (see
    ``numba.cuda.target.CUDATypingContext.resolve_value_type``)."""
    from numba.core import config
    from numba.core.dispatcher import Dispatcher

    if config.ENABLE_CUDASIM:  # the simulator runs Python: nothing is compiled for a device
        return
    from numba.cuda.dispatcher import CUDADispatcher

    for value in vars(K).values():
        if isinstance(value, Dispatcher) and not isinstance(value, CUDADispatcher):
            if not hasattr(value, "_CUDATypingContext__dispatcher"):
                value._CUDATypingContext__dispatcher = CUDADispatcher(
                    value.py_func, dict(device=True, debug=False, opt=True, inline=True))


_device_functions_without_fastmath()


def cuda_available() -> tuple[bool, str]:
    """``(ok, why not)``: whether ``numba.cuda`` can run kernels here (a driver, a device, NVVM)."""
    try:
        if not cuda.is_available():
            return False, "numba.cuda finds no CUDA driver or device"
    except Exception as exc:  # noqa: BLE001
        return False, f"numba.cuda: {exc}"
    return True, ""


@cuda.jit
def trace_kernel(P, F, seeds, tab, PT, PI, bins, books, counts):
    n = F[K.F_N]
    Q = PT.shape[0]
    one = P[K.P_ONE]
    zero = one - one
    ox, oy, oz = P[K.P_SRC_X], P[K.P_SRC_Y], P[K.P_SRC_Z]
    w0 = P[K.P_W0]
    on = 0.0
    off = 0.0
    rf = 0.0
    ab = 0.0
    c_tir = 0
    c_bounce = 0
    c_stop = 0
    c_lost = 0
    c_unconv = 0
    for ray in range(cuda.grid(1), n, cuda.gridsize(1)):
        dx, dy, dz = K.emit(P, F, seeds, tab, ray)
        qx, qy, qz, w = ox, oy, oz, w0
        if F[K.F_LENS]:
            qx, qy, qz, dx, dy, dz, w, refl, absb, code, nb = K.trace_ray(P, F, ox, oy, oz, dx, dy, dz, w0)
            rf += refl
            ab += absb
            c_bounce += nb
            c_tir += code == K.TIR_LOST
            c_stop += code == K.STOPPED
            c_lost += code == K.LOST
            c_unconv += code == K.UNCONVERGED
        if K.on_screen(P, qx, qy, qz, dx, dy, dz):
            on += w
        else:
            off += w
        if w == zero:
            continue
        zp = -one
        x = y = e = vx = vy = zero
        for p in range(Q):
            if p == 0 or PT[p, 0] != zp:
                zp = PT[p, 0]
                x, y, e, vx, vy = K.plane_values(zp, PT[p, 7], PT[p, 8], qx, qy, qz, dx, dy, dz, w)
            W = PI[p, 1]
            j = K.pixel_index(PT[p, 1], PT[p, 2], PT[p, 3], PT[p, 4], PT[p, 5], PT[p, 6], K._fl(W, one),
                              K._fl(PI[p, 0], one), W, PI[p, 2], PI[p, 3], x, y, e)
            if j >= 0:
                cuda.atomic.add(bins, j, e)
                if PI[p, 2] == 3:
                    cuda.atomic.add(bins, j + 1, vx)
                    cuda.atomic.add(bins, j + 2, vy)
    cuda.atomic.add(books, 0, on)
    cuda.atomic.add(books, 1, off)
    cuda.atomic.add(books, 2, rf)
    cuda.atomic.add(books, 3, ab)
    cuda.atomic.add(counts, 0, c_tir)
    cuda.atomic.add(counts, 1, c_bounce)
    cuda.atomic.add(counts, 2, c_stop)
    cuda.atomic.add(counts, 3, c_lost)
    cuda.atomic.add(counts, 4, c_unconv)



def _device_index(device) -> int:
    text = str(device)
    return int(text.split(":", 1)[1]) if ":" in text else 0


def trace(P, F, seeds, tab, PT, PI, total: int, device="cuda"):
    """Run the kernel on ``device``: returns ``(bins (total,), books (1, 4) float64, counts (1, 5) int64)`` on the host.

    ``P, F`` are the parameter arrays of :func:`sim.optics.engine.kernel_params` (passed as tuples),
    the rest as :func:`sim.optics.engine.trace_cpu`'s.
    """
    ok, why = cuda_available()
    if not ok:
        raise RuntimeError(f"the CUDA kernel cannot run: {why}")
    cuda.select_device(_device_index(device))
    ft = tab.dtype
    d_bins = cuda.to_device(np.zeros(max(int(total), 1), dtype=ft))
    d_books = cuda.to_device(np.zeros(len(K.BOOKS)))
    d_counts = cuda.to_device(np.zeros(len(K.COUNTS), dtype=np.int64))
    n = int(F[K.F_N])
    # Enough threads to fill the device, each looping over several rays (its books in registers).
    try:
        sms = int(cuda.get_current_device().MULTIPROCESSOR_COUNT)
    except AttributeError:  # the CUDA simulator
        sms = 1
    blocks = max(1, min((n + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK, 32 * sms))
    trace_kernel[blocks, THREADS_PER_BLOCK](K.as_tuple(P), K.as_tuple(F), cuda.to_device(seeds), cuda.to_device(tab),
                                         cuda.to_device(PT), cuda.to_device(PI), d_bins, d_books, d_counts)
    cuda.synchronize()
    return d_bins.copy_to_host(), d_books.copy_to_host()[None], d_counts.copy_to_host()[None]


def warm_up(dtype) -> None:
    """Compile the kernel for ``dtype`` by tracing no rays (``numba.cuda`` caches in memory only)."""
    ft = np.dtype(dtype)
    P = np.zeros(K.P_COUNT, dtype=ft)
    F = np.zeros(K.F_COUNT, dtype=np.int64)
    trace(P, F, np.zeros(3, np.uint64), np.zeros((4, 1), ft), np.zeros((1, 9), ft), np.zeros((1, 4), np.int64), 1)
