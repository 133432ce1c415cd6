"""The compiled ray kernel on a CUDA GPU (``numba.cuda``): one thread per ray, the CPU kernel's code.

One source, two targets. The per-ray functions of :mod:`sim.optics.kernel` (emission, the
lens, Snell, Fresnel, TIR, the books and the pixel index) are plain Python functions that
``@njit`` compiles for the CPU; here the same functions (their ``py_func``, the public
attribute of a numba dispatcher) are compiled for CUDA with ``numba.cuda.jit(device=True,
inline="always")``. Each copy is made with :class:`types.FunctionType` over a namespace of
its own (:func:`device_code`) in which every name of :mod:`sim.optics.kernel` resolves to its
CUDA copy, so a call inside a device function reaches the CUDA version, never the CPU
dispatcher. ``inline="always"`` makes numba splice each device function's IR into its
caller before typing: the kernel compiles as one function, without compiling any device
function on its own. That is what lets :func:`compile_ptx` build every kernel to PTX with
the real compiler (libNVVM) on a machine with no GPU and no driver (numba-cuda compiles a
device function called through its dispatcher for the *current device*, which needs a
driver); ``tests/sim/test_gpu_ptx.py`` does that in CI.

What differs from the CPU build: the float conversion ``_fl`` (a numba ``@overload`` on the
CPU) is a plain function per float type here (an overload for CUDA would be compiled through a
dispatcher as well), and there is no fastmath (numba.cuda's is all or nothing: no-NaN/no-inf
would let NVVM drop the kernel's ``inf`` tests; IEEE division and square root instead).

A GPU thread emits its ray (:func:`sim.optics.kernel.emit`), traces it with
:func:`sim.optics.kernel.trace_ray` (the scalar path with the full Newton loops and bounces:
a GPU has no SIMD lanes to fill) and adds it to the images with atomic adds (one image set for
the whole device; many threads per pixel make atomics the GPU's way). Each thread keeps its
energy books in registers over a grid-stride loop and adds them once at the end. The logic is
tested on CPU with numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``), the compile in CI by
:func:`compile_ptx`, and on a GPU by ``tools/gpu_check.sh``.
"""

from __future__ import annotations

import functools
import types as pytypes

import numpy as np
from numba import cuda

from sim.optics import kernel as K

__all__ = ["KERNEL_TYPES", "compile_ptx", "cuda_available", "device_code", "kernel_function", "trace", "warm_up"]

THREADS_PER_BLOCK = 256
#: The float types the tracer's kernel is built for.
KERNEL_TYPES = ("float32", "float64")


def cuda_available() -> tuple[bool, str]:
    """``(ok, why not)``: whether ``numba.cuda`` can run kernels here (numba-cuda, a driver, a device)."""
    try:
        if not cuda.is_available():
            return False, "numba.cuda finds no CUDA driver or device"
    except Exception as exc:  # noqa: BLE001 - any driver failure is a reason to report, not to crash on
        return False, f"numba.cuda: {exc}"
    return True, ""


def _fl32(x, like):
    """``x`` as float32 (``sim.optics.kernel._fl`` in a float32 kernel)."""
    return np.float32(x)


def _fl64(x, like):
    """``x`` as float64 (``sim.optics.kernel._fl`` in a float64 kernel)."""
    return np.float64(x)


def _copy(fn, namespace: dict):
    """``fn`` with its global names looked up in ``namespace`` (same code, same defaults)."""
    out = pytypes.FunctionType(fn.__code__, namespace, fn.__name__, fn.__defaults__, fn.__closure__)
    out.__qualname__ = fn.__qualname__
    out.__doc__ = fn.__doc__
    return out


@functools.cache
def device_code(dtype) -> pytypes.ModuleType:
    """The device side of the kernel for float type ``dtype``: a module holding every name of
    :mod:`sim.optics.kernel`, its compiled functions replaced by CUDA device functions of the
    same source (inlined into their callers at numba's IR level)."""
    from numba.extending import is_jitted

    ft = np.dtype(dtype)
    mod = pytypes.ModuleType(f"{__name__}.device_{ft.name}")
    ns = mod.__dict__
    ns.update({k: v for k, v in vars(K).items() if not k.startswith("__")})

    def device(fn):
        return cuda.jit(device=True, inline="always")(_copy(fn, ns))

    for name, value in vars(K).items():
        if is_jitted(value):
            ns[name] = device(value.py_func)
    ns["_fl"] = device(_fl32 if ft == np.float32 else _fl64)
    return mod


def _trace_kernel(P, F, seeds, tab, PT, PI, bins, books, counts):
    """Every ray ``cuda.grid(1) + k * gridsize`` of one LED: emission, lens, books, binning (atomic adds).

    ``K`` is :func:`device_code`'s module when compiled (see :func:`kernel_function`)."""
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


def source_digest() -> str:
    """A digest of the kernel's source (this module and :mod:`sim.optics.kernel`, whose functions it
    inlines): part of the compiled kernel's name, so numba's disk cache (keyed by the name and this
    file's time stamp) never serves a kernel built from an older ``kernel.py``."""
    import hashlib
    import inspect

    h = hashlib.sha256()
    for mod in (K, __import__(__name__, fromlist=["_"])):
        h.update(inspect.getsource(mod).encode())
    return h.hexdigest()[:12]


def kernel_function(dtype):
    """The tracer kernel's Python function for ``dtype``, its names bound to :func:`device_code` (what
    ``numba.cuda.jit`` or :func:`numba.cuda.compile_ptx` compiles)."""
    fn = _copy(_trace_kernel, {"K": device_code(dtype), "cuda": cuda})
    fn.__module__ = __name__
    fn.__qualname__ = f"trace_kernel_{np.dtype(dtype).name}_{source_digest()}"
    return fn


@functools.cache
def _kernel(dtype):
    # Cached on disk (NUMBA_CACHE_DIR moves it): the IR inlining makes the first compile take
    # tens of seconds; a later process loads the kernel.
    return cuda.jit(cache=True)(kernel_function(dtype))


def kernel_signature(dtype):
    """The numba signature of the tracer kernel for ``dtype`` (what :func:`trace` passes)."""
    from numba import types as nt

    ft = nt.float32 if np.dtype(dtype) == np.float32 else nt.float64
    return (nt.UniTuple(ft, K.P_COUNT), nt.UniTuple(nt.int64, K.F_COUNT), nt.uint64[::1], ft[:, ::1], ft[:, ::1],
            nt.int64[:, ::1], ft[::1], nt.float64[::1], nt.int64[::1])


def compile_ptx(dtype, cc=(9, 0)) -> str:
    """PTX of the tracer kernel for ``dtype`` and compute capability ``cc``, by numba-cuda's compiler
    (libNVVM): needs no GPU and no driver."""
    ptx, _ = cuda.compile_ptx(kernel_function(dtype), kernel_signature(dtype), cc=cc)
    return ptx


def _device_index(device) -> int:
    text = str(device)
    return int(text.split(":", 1)[1]) if ":" in text else 0


def trace(P, F, seeds, tab, PT, PI, total: int, device="cuda"):
    """Run the kernel on ``device``: returns ``(bins (total,), books (1, 4) float64, counts (1, 5) int64)`` on the host.

    ``P, F`` are the parameter arrays of :func:`sim.optics.engine.kernel_params`,
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
    arrays = [np.ascontiguousarray(a) for a in (seeds, tab, PT, PI)]
    _kernel(ft.name)[blocks, THREADS_PER_BLOCK](K.as_tuple(P), K.as_tuple(F), *(cuda.to_device(a) for a in arrays),
                                                d_bins, d_books, d_counts)
    cuda.synchronize()
    return d_bins.copy_to_host(), d_books.copy_to_host()[None], d_counts.copy_to_host()[None]


def warm_up(dtype) -> None:
    """Compile (or load from numba's disk cache) the kernel for ``dtype`` by tracing no rays."""
    import warnings

    from numba.core.errors import NumbaPerformanceWarning

    ft = np.dtype(dtype)
    P = np.zeros(K.P_COUNT, dtype=ft)
    F = np.zeros(K.F_COUNT, dtype=np.int64)
    with warnings.catch_warnings():  # one block on purpose: it traces no rays
        warnings.simplefilter("ignore", NumbaPerformanceWarning)
        trace(P, F, np.zeros(3, np.uint64), np.zeros((4, 1), ft), np.zeros((1, 9), ft), np.zeros((1, 4), np.int64),
              1)
