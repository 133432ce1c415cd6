"""The ring emulators the capture tests run against: the Python emulator and the C firmware.

The ``ring_backend`` fixture (tests/conftest.py) is parametrised over both; a test builds its
emulator with ``ring_backend.emulator(...)`` (RingEmulator's arguments) and passes
``ring_firmware=ring_backend.binary`` to ``pipeline.capture.session.capture``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.capture.firmware_host import ring_emulator

BACKENDS = ("python", "c")


@dataclass(frozen=True)
class RingBackend:
    """One emulator implementation: ``binary`` is the C host program, None for Python."""

    name: str
    binary: Path | None = None

    def emulator(self, led_count: int = 24, **kw):
        """A RingEmulator, or a FirmwareEmulator running the C build, with these arguments."""
        return ring_emulator(self.binary, led_count, **kw)

    def __str__(self) -> str:
        return self.name


def missing_build_tools() -> str:
    """Why the C backend cannot be built here ("" when it can): missing make, C compiler or
    firmware sources (a real build failure is an error, not a skip)."""
    import os
    import shutil

    from pipeline.capture.firmware_host import FIRMWARE_DIR

    if not (FIRMWARE_DIR / "Makefile").is_file():
        return f"no firmware sources at {FIRMWARE_DIR}"
    missing = [t for t in ("make", os.environ.get("CC", "gcc")) if shutil.which(t) is None]
    return f"{' and '.join(missing)} not found" if missing else ""
