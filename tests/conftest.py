import sys
from pathlib import Path

# Make this checkout's packages (and tests/helpers.py) importable whatever is installed.
_REPO = Path(__file__).resolve().parents[1]
for p in (str(_REPO), str(_REPO / "tests")):
    if p not in sys.path:
        sys.path.insert(0, p)


import pytest  # noqa: E402


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
