"""``iristac doctor``: check the GPU stack and compile every GPU kernel once, one line per piece.

What it checks, in order: numpy, numba and numba-cuda (versions that work together: the
``cuda`` extra of ``pyproject.toml``), libNVVM (numba-cuda's compiler back end: compiling every
GPU kernel to PTX needs it, not a GPU), every GPU kernel compiled to PTX
(:data:`GPU_KERNELS`), the CUDA driver and device (numba.cuda and torch), and on a device every
kernel compiled for it and run once on a small input. Each line starts with ``ok``, ``missing``
or ``broken``; the exit status is 1 when a line is not ``ok`` (``--cpu-only``: only the pieces a
machine without a GPU can have).
"""

from __future__ import annotations

import time

__all__ = ["GPU_KERNELS", "check", "register"]


def _tracer_ptx(dtype):
    from sim.optics import kernel_cuda

    return kernel_cuda.compile_ptx(dtype)


def _nearfield_ptx(frame_dtype):
    from pipeline.normals import gpu_nearfield

    return gpu_nearfield.compile_ptx(frame_dtype)


def _divergence_ptx(_):
    from pipeline.depth import gpu_dst

    return gpu_dst.compile_ptx()


#: (name, PTX builder, argument): every CUDA kernel of the project, for each type it is built for.
GPU_KERNELS = [
    ("ray tracer (sim.optics.kernel_cuda), float32", _tracer_ptx, "float32"),
    ("ray tracer (sim.optics.kernel_cuda), float64", _tracer_ptx, "float64"),
    ("near-field normals (pipeline.normals.gpu_nearfield), uint8", _nearfield_ptx, "uint8"),
    ("near-field normals (pipeline.normals.gpu_nearfield), uint16", _nearfield_ptx, "uint16"),
    ("DST divergence (pipeline.depth.gpu_dst), float32", _divergence_ptx, None),
]


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=__doc__.split("\n\n")[0])
    p.add_argument("--cpu-only", action="store_true", help="only what a machine without a GPU can have "
                   "(packages, libNVVM, PTX); the driver and device are not required")
    p.add_argument("--no-compile", action="store_true", help="skip compiling the kernels (about a minute)")
    p.set_defaults(func=_run)


def _version(dist: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def _release(version: str) -> tuple[int, ...]:
    """The leading numbers of a version string (``2.4.6`` -> ``(2, 4, 6)``)."""
    out = []
    for part in version.split("."):
        digits = "".join(ch for ch in part if ch.isdigit()) if part[:1].isdigit() else ""
        if not digits:
            break
        out.append(int(digits))
    return tuple(out)


def _packages():
    """``(status, line)`` of numpy, numba, numba-cuda (and whether they fit together)."""
    out = []
    np_v, nb_v, nc_v = _version("numpy"), _version("numba"), _version("numba-cuda")
    out.append(("ok", f"numpy {np_v}"))
    out.append(("ok" if nb_v else "missing", f"numba {nb_v}" if nb_v else "numba: not installed"))
    if nc_v is None:
        out.append(("missing", "numba-cuda: not installed (pip install 'iristac[cuda]')"))
    elif np_v and _release(nc_v) < (0, 31) and _release(np_v) >= (2, 5):
        out.append(("broken", f"numba-cuda {nc_v} with numpy {np_v}: numba-cuda < 0.31 fails at import on numpy "
                              f">= 2.5 (np.row_stack is gone); pip install 'numpy<2.5' or 'iristac[cuda]'"))
    else:
        out.append(("ok", f"numba-cuda {nc_v}"))
    return out, nc_v is not None


def nvvm_status() -> tuple[str, str]:
    """``("ok", line)`` when libNVVM compiles a tiny kernel to PTX (no GPU or driver needed), else
    ``("missing", line)`` saying what to install; ``line`` is what ``iristac doctor`` prints."""
    try:
        from numba import cuda

        def k(a):
            a[0] = 1.0

        from numba import types as nt

        t = time.perf_counter()
        cuda.compile_ptx(k, (nt.float32[::1],), cc=(9, 0))
        return "ok", f"libNVVM: compiles PTX ({time.perf_counter() - t:.1f} s)"
    except Exception as exc:  # noqa: BLE001 - reported, one line
        return "missing", f"libNVVM: cannot compile ({type(exc).__name__}: {str(exc).splitlines()[0][:160]}); " \
                          f"pip install 'iristac[cuda]' (its CUDA wheels carry libNVVM)"


def _ptx_lines():
    out = []
    for name, build, arg in GPU_KERNELS:
        t = time.perf_counter()
        try:
            ptx = build(arg)
            out.append(("ok", f"PTX {name}: {len(ptx) // 1024} KiB in {time.perf_counter() - t:.1f} s"))
        except Exception as exc:  # noqa: BLE001 - reported, one line
            out.append(("broken", f"PTX {name}: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}"))
    return out


def _driver_lines(compile_kernels: bool):
    out = []
    from sim.optics.kernel_cuda import cuda_available

    ok, why = cuda_available()
    if not ok:
        return [("missing", f"CUDA device (numba.cuda): {why}")], False
    from numba import cuda

    dev = cuda.get_current_device()
    name = dev.name.decode() if isinstance(dev.name, bytes) else dev.name
    out.append(("ok", f"CUDA device (numba.cuda): {name}, compute capability {dev.compute_capability}"))
    try:
        import torch

        if torch.cuda.is_available():
            out.append(("ok", f"torch {torch.__version__}: {torch.cuda.get_device_name(0)}"))
        else:
            out.append(("missing", f"torch {torch.__version__} sees no CUDA device (a CPU build?)"))
    except ImportError:
        out.append(("missing", "torch: not installed"))
    if compile_kernels:
        out += _run_lines()
    return out, True


def _run_lines():
    """Every kernel compiled for the device and run once on a small input."""
    import numpy as np

    out = []
    for dt in ("float32", "float64"):
        t = time.perf_counter()
        try:
            from sim.optics import engine
            from sim.scene import load_scene

            s = load_scene("default")
            from sim.optics.grid import ImageBins, PixelGrid

            lay = ImageBins(PixelGrid((8, 8), (7.0, 7.0), s.plane.z), [0.0], vector=True).layout
            (img,), tr = engine.trace_led(s, [lay], rays=4096, sampler="random", device="cuda", dtype=dt)
            (ref,), tr0 = engine.trace_led(s, [lay], rays=4096, sampler="random", dtype=dt)
            # The same rays: a ray whose last bit rounds differently may land one pixel over, so
            # a few per thousand of the image, never more; the books agree to rounding.
            de = abs(tr.energy.on_screen - tr0.energy.on_screen)
            err = float(np.abs(img - ref).sum() / max(np.abs(ref).sum(), 1e-30))
            out.append(("ok" if de < 1e-3 and err < 1e-2 else "broken",
                        f"run ray tracer {dt} on the GPU: {time.perf_counter() - t:.1f} s with the compile; "
                        f"on-screen energy differs by {de:.1e}, image by {err:.1e} of the CPU's, counters "
                        f"{'equal' if tr.counters == tr0.counters else f'{tr.counters} vs {tr0.counters}'}"))
        except Exception as exc:  # noqa: BLE001 - reported, one line
            out.append(("broken", f"run ray tracer {dt} on the GPU: {type(exc).__name__}: {str(exc)[:200]}"))
    t = time.perf_counter()
    try:
        import torch

        from pipeline.normals.batched import NearFieldBatched
        from pipeline.normals.gpu_nearfield import NearFieldGPU

        rng = np.random.default_rng(0)
        L = rng.normal(size=(6, 3, 5, 7, 3))
        L[..., 2] = np.abs(L[..., 2]) + 1.0
        frames = rng.integers(0, 255, size=(2, 6, 5, 7, 3), dtype=np.uint8)
        a = NearFieldGPU(L).solve(torch.as_tensor(frames, device="cuda"))
        b = NearFieldBatched(L, device="cuda").solve(frames)
        d = float((a["normals"] - b["normals"]).abs().max())
        out.append(("ok" if d < 1e-4 else "broken", f"run near-field normals on the GPU: "
                    f"{time.perf_counter() - t:.1f} s with the compile; largest difference from the torch solver {d:.1e}"))
    except Exception as exc:  # noqa: BLE001 - reported, one line
        out.append(("broken", f"run near-field normals on the GPU: {type(exc).__name__}: {str(exc)[:200]}"))
    return out


def check(cpu_only: bool = False, compile_kernels: bool = True) -> list[tuple[str, str]]:
    """The doctor's ``(status, line)`` pairs (see the module docstring)."""
    lines, have_cuda = _packages()
    if not have_cuda:
        return lines
    lines.append(nvvm_status())
    if compile_kernels and lines[-1][0] == "ok":
        lines += _ptx_lines()
    if not cpu_only:
        more, _ = _driver_lines(compile_kernels)
        lines += more
    return lines


def _run(args) -> int:
    bad = 0
    for status, line in check(cpu_only=args.cpu_only, compile_kernels=not args.no_compile):
        print(f"{status:<8}{line}", flush=True)
        bad += status != "ok"
    return 1 if bad else 0
