"""The C ring firmware's host build as a drop-in for :class:`~pipeline.capture.emulator.RingEmulator`.

``firmware/`` (beside the packages in a checkout; not installed by pip) holds the ring's
firmware: a portable C99 protocol core and a host build, ``iristac-ring-host``, that serves it
behind a pseudo-terminal with the Python emulator's fault options. :class:`FirmwareEmulator`
runs that program and gives it the emulator's interface (``path``, ``stats``,
``history()``, ``states_during()``, ``led_state()``), so the capture code, the virtual camera
(which renders whatever the ring latched) and the tests run unchanged against the C code that
goes onto the microcontroller.

Ground truth crosses the process boundary through two files the program keeps current: a
latch log (every latched LED state with its ``CLOCK_MONOTONIC`` time, written before the reply
that confirms it, so whoever saw the ACK finds the state) and a memory-mapped block of
counters. ``time.monotonic()`` is ``CLOCK_MONOTONIC`` on Linux, so latch times compare with
the camera's exposure times directly; :meth:`FirmwareEmulator.start` checks that they do.

Examples
--------
>>> from pipeline.capture.client import RingClient
>>> binary = build_host_firmware()                       # doctest: +SKIP
>>> with FirmwareEmulator(binary, led_count=4) as emu, RingClient(emu.path) as ring:  # doctest: +SKIP
...     _ = ring.show_pattern(np.full((4, 3), 0.5), 1.0)
...     emu.led_state()[1], ring.info.firmware
(1.0, 'iristac-ring-c/1')
"""

from __future__ import annotations

import os
import select
import shutil
import signal
import struct
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from pipeline.base.errors import UserError
from pipeline.capture import protocol as P
from pipeline.capture.emulator import EmulatorStats, FaultSpec, LatchHistory, RingEmulator, ShownState

__all__ = ["FIRMWARE_DIR", "HOST_PROGRAM", "build_host_firmware", "FirmwareEmulator", "ring_emulator"]

#: The firmware sources of this checkout (absent from an installed wheel).
FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "firmware"
#: Name of the host build's program under ``BUILD/host/``.
HOST_PROGRAM = "iristac-ring-host"

# The counters of `--stats` in the order ring_host.c writes them (11 native uint64).
_STATS_FIELDS = ("commands", "dropped_in", "dropped_out", "corrupted_in", "corrupted_out",
                 "delayed", "duplicates", "crc_errors", "resyncs", "bytes_in", "bytes_out")
_STATS = struct.Struct(f"={len(_STATS_FIELDS)}Q")
_RECORD_HEAD = struct.Struct("=qBB")  # CLOCK_MONOTONIC ns, LED count, brightness


def build_host_firmware(build_dir: str | os.PathLike | None = None, *,
                        firmware_dir: str | os.PathLike = FIRMWARE_DIR) -> Path:
    """Build the host program with ``make -C firmware host`` and return its path.

    Parameters
    ----------
    build_dir : path-like, optional
        Where the build goes (``make BUILD=...``); default ``firmware/build``.
    firmware_dir : path-like
        The firmware sources (default: this checkout's ``firmware/``).

    Returns
    -------
    Path
        ``BUILD/host/iristac-ring-host``.

    Raises
    ------
    UserError
        No ``firmware/`` sources (an installed package has none), no ``make`` or C compiler,
        or the build failed (with the compiler's last lines).
    """
    src = Path(firmware_dir)
    if not (src / "Makefile").is_file():
        raise UserError(f"the ring firmware sources are not at {src} (firmware/ comes with the "
                        "repository, not with the installed package)")
    missing = [tool for tool in ("make", os.environ.get("CC", "gcc")) if shutil.which(tool) is None]
    if missing:
        raise UserError(f"cannot build the ring firmware's host program: {' and '.join(missing)} "
                        "not found (install a C compiler and make)")
    build = Path(build_dir).resolve() if build_dir is not None else src / "build"
    r = subprocess.run(["make", "-s", "-C", str(src), "host", f"BUILD={build}"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-15:])
        raise UserError(f"make -C {src} host failed:\n{tail}")
    return build / "host" / HOST_PROGRAM


class FirmwareEmulator:
    """The ring served by the C firmware's host build, with the emulator's interface.

    Parameters
    ----------
    binary : path-like
        The host program (:func:`build_host_firmware`).
    led_count, version, faults, baudrate, seed, firmware
        As for :class:`~pipeline.capture.emulator.RingEmulator` (``firmware`` is the id HELLO
        reports); faults are drawn by the C program's own generator, so a seed gives other
        (equally reproducible) faults than in the Python emulator.
    """

    def __init__(
        self,
        binary: str | os.PathLike,
        led_count: int = 24,
        *,
        version: int = P.PROTOCOL_VERSION,
        faults: FaultSpec | None = None,
        baudrate: float | None = None,
        seed: int = 0,
        firmware: str = "iristac-ring-c/1",
    ) -> None:
        self.binary = Path(binary)
        if not 1 <= led_count <= 24:
            raise ValueError(f"led_count must be in 1..24 (the firmware's RING_MAX_LEDS), got {led_count}")
        self.led_count = led_count
        self.version = version
        self.faults = faults or FaultSpec()
        self.baudrate = baudrate
        self.seed = seed
        self.firmware = firmware
        self.path: str | None = None
        self._disconnected = threading.Event()
        self._proc: subprocess.Popen | None = None
        self._dir: Path | None = None
        self._log = None
        self._stats_fd: int | None = None
        self._final_stats: EmulatorStats | None = None
        self._lock = threading.Lock()  # one reader of the log at a time
        self._tail = b""
        self._history = LatchHistory()

    # ------------------------------------------------------------------ lifecycle
    def _args(self) -> list[str]:
        f = self.faults
        spec = f"drop={f.drop!r},corrupt={f.corrupt!r},delay={f.delay!r},delay-s={f.delay_s!r}"
        if f.disconnect_after is not None:
            spec += f",disconnect-after={f.disconnect_after}"
        args = [str(self.binary), "--leds", str(self.led_count), "--protocol-version",
                str(self.version), "--firmware-id", self.firmware, "--seed", str(self.seed),
                "--latch-log", str(self._dir / "latches.bin"), "--stats", str(self._dir / "stats.bin")]
        if f.any:
            args += ["--faults", spec]
        if self.baudrate:
            args += ["--baud", repr(float(self.baudrate))]
        return args

    def start(self) -> str:
        """Start the program; return the pty path it serves (for the host to open)."""
        if self._proc is not None:
            return self.path  # type: ignore[return-value]
        if not self.binary.is_file():
            raise UserError(f"ring firmware host program {self.binary} not found (build it with "
                            "make -C firmware host)")
        self._dir = Path(tempfile.mkdtemp(prefix="iristac-ring-host-"))
        err = open(self._dir / "stderr.txt", "wb")
        t_spawn = time.monotonic()
        try:
            self._proc = subprocess.Popen(self._args(), stdout=subprocess.PIPE, stderr=err,
                                          stdin=subprocess.DEVNULL)
        finally:
            err.close()
        ready, _, _ = select.select([self._proc.stdout], [], [], 10.0)
        line = self._proc.stdout.readline().decode().strip() if ready else ""  # type: ignore[union-attr]
        if not line.startswith("/"):
            self._proc.kill()
            self._proc.wait()
            msg = (self._dir / "stderr.txt").read_text(errors="replace").strip()
            self._cleanup()
            raise UserError(f"ring firmware host program {self.binary} did not start: "
                            f"{msg or 'no device path printed'}")
        self.path = line
        self._log = open(self._dir / "latches.bin", "rb")
        self._stats_fd = os.open(self._dir / "stats.bin", os.O_RDONLY)
        self._read_log()
        if not len(self._history) or abs(self._history.all()[0].t - t_spawn) > 5.0:
            self.stop()
            raise UserError("the ring firmware host program's CLOCK_MONOTONIC does not match "
                            "time.monotonic(): its latch times cannot be compared with frames")
        return self.path

    def stop(self) -> None:
        """Stop the program (SIGTERM) and remove its files; history and stats stay readable."""
        proc = self._proc
        if proc is None:
            return
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if proc.returncode == 1:
            self._disconnected.set()
        if self._log is not None:
            self._read_log()
            self._final_stats = self._read_stats()
        self._cleanup()

    def _cleanup(self) -> None:
        if self._proc is not None and self._proc.stdout is not None:
            self._proc.stdout.close()
        if self._log is not None:
            self._log.close()
            self._log = None
        if self._stats_fd is not None:
            os.close(self._stats_fd)
            self._stats_fd = None
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the program exits (disconnect or :meth:`stop`); True if it did."""
        if self._proc is None:
            return True
        try:
            code = self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return False
        if code == 1:
            self._disconnected.set()
        return True

    @property
    def disconnected(self) -> threading.Event:
        """Set once the program has exited after an injected disconnect (exit status 1)."""
        if self._proc is not None and self._proc.poll() == 1:
            self._disconnected.set()
        return self._disconnected

    def __enter__(self) -> FirmwareEmulator:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ ground truth
    @property
    def stats(self) -> EmulatorStats:
        """The program's counters now (after :meth:`stop`: their final values)."""
        if self._stats_fd is None:
            return self._final_stats or EmulatorStats()
        return self._read_stats()

    def _read_stats(self) -> EmulatorStats:
        raw = os.pread(self._stats_fd, _STATS.size, 0)  # type: ignore[arg-type]
        if len(raw) < _STATS.size:
            return EmulatorStats()
        return EmulatorStats(**dict(zip(_STATS_FIELDS, _STATS.unpack(raw))))

    def _read_log(self) -> None:
        """Parse the latch records appended since the last call (a partial one waits)."""
        with self._lock:
            if self._log is None:
                return
            data = self._tail + self._log.read()
            size = _RECORD_HEAD.size + 3 * self.led_count
            n = len(data) // size
            for i in range(n):
                t_ns, count, brightness = _RECORD_HEAD.unpack_from(data, i * size)
                if count != self.led_count:
                    raise UserError(f"ring firmware latch log: a record of {count} LEDs, "
                                    f"expected {self.led_count}")
                start = i * size + _RECORD_HEAD.size
                levels = np.frombuffer(data, np.uint8, 3 * count, start).reshape(count, 3).copy()
                self._history.append(ShownState(t_ns * 1e-9, levels, int(brightness)))
            self._tail = data[n * size:]

    def led_state(self) -> tuple[np.ndarray, float]:
        """What the LEDs show now: drive (L, 3) float32 in [0, 1] and brightness in [0, 1]."""
        self._read_log()
        s = self._history.last()
        return s.levels.astype(np.float32) / 255.0, s.brightness / 255.0

    def history(self) -> list[ShownState]:
        """Every latched state since start, oldest first (the first is all-off at power-on)."""
        self._read_log()
        return self._history.all()

    def states_during(self, t0: float, t1: float) -> list[ShownState]:
        """The states shown at any instant of the closed interval [t0, t1] (monotonic s)."""
        self._read_log()
        return self._history.during(t0, t1)


def ring_emulator(ring_firmware: str | os.PathLike | None = None, led_count: int = 24, **kw):
    """An emulated ring: :class:`~pipeline.capture.emulator.RingEmulator`, or with
    ``ring_firmware`` (the host program) a :class:`FirmwareEmulator`; ``kw`` as for either.

    >>> type(ring_emulator(None, 4)).__name__
    'RingEmulator'
    """
    if ring_firmware is None:
        return RingEmulator(led_count, **kw)
    return FirmwareEmulator(ring_firmware, led_count, **kw)
