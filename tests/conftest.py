"""Shared fixtures: every test of a numeric kernel that has a device or a float type takes
``device`` and ``dtype`` from here, so each runs on the CPU (and on CUDA where one is present)
and in float32 as well as float64, with tolerances that depend on the float type."""

import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

# Make this checkout's packages (and tests/helpers.py) importable whatever is installed.
_REPO = Path(__file__).resolve().parents[1]
for p in (str(_REPO), str(_REPO / "tests")):
    if p not in sys.path:
        sys.path.insert(0, p)


def _devices() -> list[str]:
    import torch

    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@dataclass(frozen=True)
class FloatType:
    """A float type under test: its name, numpy and torch types, and tolerances that scale
    with its precision (``eps`` is the machine epsilon)."""

    name: str

    @property
    def np(self):
        return np.dtype(self.name)

    @property
    def torch(self):
        import torch

        return getattr(torch, self.name)

    @property
    def eps(self) -> float:
        return float(np.finfo(self.name).eps)

    def tol(self, float64: float, float32: float) -> float:
        """The tolerance for this type: ``float64``'s or ``float32``'s."""
        return float64 if self.name == "float64" else float32

    def __str__(self) -> str:
        return self.name


@pytest.fixture(params=_devices())
def device(request) -> str:
    """A torch device: ``cpu``, and ``cuda`` when a GPU is present."""
    return request.param


@pytest.fixture(params=["float32", "float64"])
def dtype(request) -> FloatType:
    """A float type: float32 (the solvers' default) and float64 (the reference)."""
    return FloatType(request.param)


# ---- the tracer's PTX, compiled beside the rest of the suite -----------------------------------

#: The test that needs :func:`tracer_ptx` (about 25 s of one core: numba-cuda inlines every
#: device function of the branch-free kernel before libNVVM compiles it).
_PTX_TEST = "test_cuda_kernel_compiles_to_ptx"
_PTX_JOB = pytest.StashKey[tuple]()
_PTX_SCRIPT = r"""
import sys
from pathlib import Path
from pipeline.cli.doctor import nvvm_status
from sim.optics import kernel_cuda
status, line = nvvm_status()
out = Path(sys.argv[1])
out.write_text("ok\n" + kernel_cuda.compile_ptx("float32") if status == "ok" else "skip\n" + line)
"""


def _compile_tracer_ptx(out: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(_REPO), os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen([sys.executable, "-c", _PTX_SCRIPT, str(out)], cwd=str(_REPO), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def pytest_collection_modifyitems(session, config, items):
    """Start the tracer's PTX compile in a background process once the run is known to hold its
    test among others, so the compile overlaps them; the test waits for it (its outcome does
    not depend on when the compile ends, only the suite's wall time does). Not in a parallel
    worker (pytest-xdist): every worker collects every test, and only one runs it; there the
    test compiles when it runs, while the other workers go on."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return
    if len(items) > 1 and any(item.name == _PTX_TEST for item in items):
        out = Path(tempfile.mkdtemp(prefix="iristac-ptx-")) / "ptx.txt"
        config.stash[_PTX_JOB] = (_compile_tracer_ptx(out), out)


@pytest.fixture(scope="session")
def tracer_ptx(request) -> tuple[str, str]:
    """``("ok", ptx)`` of the tracer kernel in float32 by the real numba-cuda compiler, or
    ``("skip", why)`` where libNVVM cannot compile."""
    proc, out = request.config.stash.get(_PTX_JOB, (None, None))
    if proc is None:
        out = Path(tempfile.mkdtemp(prefix="iristac-ptx-")) / "ptx.txt"
        proc = _compile_tracer_ptx(out)
    _, err = proc.communicate(timeout=900)
    if proc.returncode != 0:
        raise AssertionError(f"the tracer's PTX compile failed (exit {proc.returncode}):\n{err[-3000:]}")
    status, _, text = out.read_text().partition("\n")
    return status, text


def pytest_sessionfinish(session, exitstatus):
    """Fail the run if a module of the project was imported from outside this checkout.

    An editable install of another checkout can serve a module this one moved or deleted
    (``import sim.frames`` would then still work here), hiding a stale import.
    """
    outside = sorted(
        name for name, mod in list(sys.modules.items())
        if name.split(".")[0] in ("sim", "calibration", "pipeline", "data_schemas")
        and getattr(mod, "__file__", None) and _REPO not in Path(mod.__file__).resolve().parents)
    if outside:
        print(f"\nmodules imported from outside {_REPO}: {', '.join(outside)}", file=sys.stderr)
        session.exitstatus = 1
    proc, _ = session.config.stash.get(_PTX_JOB, (None, None))
    if proc is not None and proc.poll() is None:  # its test did not run (deselected, -x stop)
        proc.kill()
        proc.wait()
@pytest.fixture(scope="session")
def ring_firmware_binary(tmp_path_factory):
    """The C ring firmware's host program (``make -C firmware host``), built once per session
    into a temporary folder; skips with the reason when make or a C compiler is missing."""
    from pipeline.capture.firmware_host import build_host_firmware
    from ring_backends import missing_build_tools

    why = missing_build_tools()
    if why:
        pytest.skip(f"C ring firmware backend not built: {why}")
    return build_host_firmware(tmp_path_factory.mktemp("ring-firmware"))


@pytest.fixture(scope="session", params=["python", "c"])
def ring_backend(request):
    """The ring emulator backend: the Python emulator, and the C firmware's host build."""
    from ring_backends import RingBackend

    if request.param == "python":
        return RingBackend("python")
    return RingBackend("c", request.getfixturevalue("ring_firmware_binary"))
