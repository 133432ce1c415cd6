"""An MCU emulator of the LED ring behind a real pseudo-terminal, with fault injection.

The emulator opens a pty pair (``os.openpty``), serves the ring protocol on the master side in
a background thread and hands out the slave's device path, so the host talks to it through
the real pyserial ``Serial`` class exactly as it would to a USB-serial MCU. The device itself
is :class:`RingDevice`, the protocol behaviour without I/O (the Python twin of the C firmware
in ``firmware/``; both pass the conformance vectors ``firmware/vectors/protocol.vec``).

Faults act on whole frames as they cross the emulated wire, in both directions:

- ``drop=P``: the frame is lost (the device never sees a command / the host never sees a reply);
- ``corrupt=P``: one random bit of the frame is flipped, and the corrupted bytes go through
  the receiver's real parser (which must detect it by CRC and resynchronise);
- ``delay=P``: before handling a command the device stalls for ``delay-s`` seconds
  (default 0.05), as a busy MCU would, so late and duplicate replies reach the host;
- ``disconnect-after=N``: the device handles N commands, then "is unplugged" when the next
  frame arrives: the pty is closed and the host's read fails.

With any fault enabled the host's bytes are split into frames before they cross the wire;
without, they reach the device exactly as sent (garbage included).

With ``baudrate`` set, every frame also costs its time on a UART line (10 bits per byte), so
benchmarks can separate the protocol's own overhead from the wire time.

The emulator keeps the ground truth: every latch (SHOW or OFF) is recorded with its
``time.monotonic()`` time, so :meth:`RingEmulator.states_during` tells what the LEDs showed
during any camera exposure.

Examples
--------
>>> import serial
>>> from pipeline.capture.client import RingClient
>>> with RingEmulator(led_count=24) as emu:
...     with RingClient(emu.path, timeout=0.2) as ring:
...         _ = ring.show_pattern(np.eye(24, 3), 1.0)
...     drive, brightness = emu.led_state()
>>> drive[:3].tolist(), brightness
([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], 1.0)
"""

from __future__ import annotations

import bisect
import os
import random
import select
import threading
import time
import tty
from dataclasses import dataclass, fields
from typing import Callable

import numpy as np

from pipeline.base.errors import UserError
from pipeline.capture import protocol as P

__all__ = [
    "FaultSpec", "parse_faults", "ShownState", "LatchHistory", "EmulatorStats", "RingDevice",
    "RingEmulator",
    "serve_forever",
]


@dataclass(frozen=True)
class FaultSpec:
    """Fault probabilities per frame and the disconnect point (see the module docstring)."""

    drop: float = 0.0
    corrupt: float = 0.0
    delay: float = 0.0
    delay_s: float = 0.05
    disconnect_after: int | None = None

    def __post_init__(self) -> None:
        for name in ("drop", "corrupt", "delay"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise UserError(f"--faults: {name}={value} must be a probability in [0, 1]")
        if self.delay_s < 0:
            raise UserError(f"--faults: delay-s={self.delay_s} must be >= 0 seconds")
        if self.disconnect_after is not None and self.disconnect_after < 1:
            raise UserError(
                f"--faults: disconnect-after={self.disconnect_after} must be a positive count"
            )

    @property
    def any(self) -> bool:
        """True when any fault is enabled."""
        return bool(self.drop or self.corrupt or self.delay or self.disconnect_after)


def parse_faults(spec: str | None) -> FaultSpec:
    """Parse ``"drop=0.05,corrupt=0.05,delay=0.02,delay-s=0.05,disconnect-after=N"``.

    Parameters
    ----------
    spec : str or None
        Comma-separated ``key=value`` pairs; empty or None means no faults.

    Returns
    -------
    FaultSpec

    Raises
    ------
    UserError
        Naming the key and what was expected when the spec is malformed.

    Examples
    --------
    >>> parse_faults("drop=0.05,disconnect-after=40")
    FaultSpec(drop=0.05, corrupt=0.0, delay=0.0, delay_s=0.05, disconnect_after=40)
    """
    if not spec:
        return FaultSpec()
    known = {f.name.replace("_", "-"): f.name for f in fields(FaultSpec)}
    values: dict[str, float | int] = {}
    for item in spec.split(","):
        item = item.strip()
        if not item:
            continue
        key, sep, raw = item.partition("=")
        key = key.strip().lower()
        if not sep or key not in known:
            raise UserError(
                f"--faults: cannot parse {item!r}; expected key=value with key one of "
                f"{', '.join(sorted(known))}"
            )
        try:
            value: float | int = int(raw) if key == "disconnect-after" else float(raw)
        except ValueError:
            kind = "an integer" if key == "disconnect-after" else "a number"
            raise UserError(f"--faults: {key}={raw!r} is not {kind}") from None
        values[known[key]] = value
    return FaultSpec(**values)


@dataclass(frozen=True)
class ShownState:
    """What the LEDs showed from time ``t`` (``time.monotonic()``) until the next latch."""

    t: float
    levels: np.ndarray  # (L, 3) uint8
    brightness: int  # 0..255

    def same_as(self, levels: np.ndarray, brightness: int) -> bool:
        """True when this state equals the given 8-bit levels and brightness."""
        return int(self.brightness) == int(brightness) and np.array_equal(self.levels, levels)


class LatchHistory:
    """The states a ring latched, with their times: what the LEDs showed at any instant.

    Thread-safe (the device appends while the camera reads). Shared by :class:`RingDevice`
    and :class:`~pipeline.capture.firmware_host.FirmwareEmulator`.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._states: list[ShownState] = []
        self._times: list[float] = []

    def append(self, state: ShownState) -> None:
        with self._lock:
            self._states.append(state)
            self._times.append(state.t)

    def last(self) -> ShownState:
        with self._lock:
            return self._states[-1]

    def all(self) -> list[ShownState]:
        with self._lock:
            return list(self._states)

    def __len__(self) -> int:
        return len(self._states)

    def during(self, t0: float, t1: float) -> list[ShownState]:
        """The states shown at any instant of the closed interval [t0, t1]."""
        if t1 < t0:
            raise ValueError(f"interval end {t1} is before its start {t0}")
        with self._lock:
            i0 = max(bisect.bisect_right(self._times, t0) - 1, 0)
            i1 = bisect.bisect_right(self._times, t1)
            return self._states[i0:i1]


@dataclass
class EmulatorStats:
    """Counters of what crossed the emulated wire (for tests and the benchmark)."""

    commands: int = 0
    dropped_in: int = 0
    dropped_out: int = 0
    corrupted_in: int = 0
    corrupted_out: int = 0
    delayed: int = 0
    duplicates: int = 0
    crc_errors: int = 0  # frames the device dropped: bad CRC, bad length or frame gap
    resyncs: int = 0  # of which partial frames dropped at a frame gap
    bytes_in: int = 0
    bytes_out: int = 0


class RingDevice:
    """The ring MCU's protocol behaviour without any I/O: bytes in, reply frames out.

    The Python twin of the C firmware core (``firmware/core/ring_device.c``): both pass the
    conformance vectors of ``firmware/vectors/protocol.vec``. Replies go to ``send`` (one whole
    frame per call); time comes from ``clock`` (seconds), so tests can drive it exactly.

    Call :meth:`receive` with the bytes that arrived and :meth:`poll` while the line is idle.
    A frame dropped for a bad CRC or length, or a partial frame dropped when the line stayed
    idle for longer than ``frame_gap_s``, makes the device send one ``NAK BAD_CRC`` once it
    has processed everything received so far.

    Parameters
    ----------
    led_count : int
    version : int
        Protocol version reported by HELLO.
    firmware : str
        Firmware identifier reported by HELLO (first 32 bytes).
    send : callable (bytes) -> None
        Where reply frames go.
    clock : callable () -> float
        Seconds (``time.monotonic`` by default; latch times in :meth:`history` use it).
    frame_gap_s : float
        Inter-byte timeout after which a partial frame is dropped.
    stats : EmulatorStats, optional
        Counters to update (``commands``, ``duplicates``, ``crc_errors``, ``resyncs``).

    Examples
    --------
    >>> out = []
    >>> dev = RingDevice(4, send=out.append)
    >>> dev.receive(bytes.fromhex("a5000704 8f15"))   # SHOW, seq 7 (the spec's example)
    >>> P.FrameParser().feed(out[0])[0].payload[:5].hex(" ")   # ACK SHOW, latch_count 1
    '04 01 00 00 00'
    """

    FRAME_GAP_S = 0.002

    def __init__(
        self,
        led_count: int = 24,
        *,
        version: int = P.PROTOCOL_VERSION,
        firmware: str = "iristac-ring-emulator/1",
        send: Callable[[bytes], None],
        clock: Callable[[], float] = time.monotonic,
        frame_gap_s: float = FRAME_GAP_S,
        stats: EmulatorStats | None = None,
    ) -> None:
        if not 1 <= led_count <= (P.MAX_PAYLOAD - 1) // 3:
            raise ValueError(f"led_count must be in 1..{(P.MAX_PAYLOAD - 1) // 3}, got {led_count}")
        self.led_count = led_count
        self.version = version
        self.firmware = firmware
        self.frame_gap_s = frame_gap_s
        self.stats = stats if stats is not None else EmulatorStats()
        self._send = send
        self._clock = clock
        off = np.zeros((led_count, 3), np.uint8)
        self._pending = off.copy()
        self._pending_brightness = 0
        self._history = LatchHistory()
        self._history.append(ShownState(clock(), off, 0))
        self._latch_count = 0
        self._last_key: tuple[int, int, bytes] | None = None
        self._last_reply = b""
        self._parser = P.FrameParser()
        self._last_rx = clock()
        self._dropped = 0  # parser drops already counted in stats.crc_errors
        self._nak_due = False

    # ------------------------------------------------------------------ the line
    @property
    def pending(self) -> int:
        """Bytes of a partial frame buffered (non-zero: call :meth:`poll` within a frame gap)."""
        return self._parser.pending

    def receive(self, data: bytes) -> None:
        """Bytes arrived: execute and answer every complete frame, in order."""
        self._last_rx = self._clock()
        self._run(self._parser.iter_feed(data))

    def poll(self) -> None:
        """The line is idle: after a frame gap, a buffered partial frame will never complete
        (a corrupted LEN); drop it START by START, rescanning what it held."""
        if self._parser.pending and self._clock() - self._last_rx > self.frame_gap_s:
            self.stats.resyncs += 1
            self.stats.crc_errors += 1
            self._nak_due = True
            self._run(self._parser.iter_resync())
        else:
            self._flush_nak()

    def _run(self, frames) -> None:
        for frame in frames:
            self._count_drops()
            self._handle(frame)
        self._count_drops()
        self._flush_nak()

    def _count_drops(self) -> None:
        dropped = self._parser.crc_errors + self._parser.length_errors
        if dropped != self._dropped:
            self.stats.crc_errors += dropped - self._dropped
            self._dropped = dropped
            self._nak_due = True

    def _flush_nak(self) -> None:
        if self._nak_due:
            # The sender's SEQ is unknown when a frame is bad: NAK with SEQ 0 so the host resends.
            self._nak_due = False
            self._send(P.encode_frame(P.Frame(0, P.Command.NAK, bytes((0, P.NakCode.BAD_CRC)))))

    def _handle(self, frame: P.Frame) -> None:
        self.stats.commands += 1
        key = (frame.seq, frame.cmd, frame.payload)
        if key == self._last_key:
            # A retransmission of the command just executed: answer from the reply cache and
            # do not execute it again (a repeated SHOW must not add a latch).
            self.stats.duplicates += 1
            reply = self._last_reply
        else:
            reply = P.encode_frame(self._execute(frame))
            self._last_key, self._last_reply = key, reply
        self._send(reply)

    def _execute(self, frame: P.Frame) -> P.Frame:
        C = P.Command
        cmd, data = frame.cmd, frame.payload

        def ack(extra: bytes = b"") -> P.Frame:
            return P.Frame(frame.seq, C.ACK, bytes((cmd,)) + extra)

        def nak(code: P.NakCode) -> P.Frame:
            return P.Frame(frame.seq, C.NAK, bytes((cmd, code)))

        if cmd == C.HELLO:
            # Answered whatever the payload says: any host must learn this device's version.
            return ack(P.encode_hello(P.Hello(self.version, self.led_count, self.firmware)))
        if cmd == C.SET_ALL:
            if len(data) != 3 * self.led_count + 1:
                return nak(P.NakCode.BAD_LENGTH)
            self._pending, self._pending_brightness = P.parse_state_payload(data, self.led_count)
            return ack()
        if cmd == C.SET_ONE:
            if len(data) != 4:
                return nak(P.NakCode.BAD_LENGTH)
            if data[0] >= self.led_count:
                return nak(P.NakCode.BAD_ARGUMENT)
            self._pending[data[0]] = np.frombuffer(data[1:], np.uint8)
            return ack()
        if cmd in (C.SHOW, C.OFF, C.STATUS):
            if data:
                return nak(P.NakCode.BAD_LENGTH)
            if cmd == C.OFF:
                self._pending = np.zeros((self.led_count, 3), np.uint8)
                self._pending_brightness = 0
            if cmd != C.STATUS:
                self._latch(self._pending.copy(), self._pending_brightness)
            return ack(P.encode_status(self._status()))
        return nak(P.NakCode.UNKNOWN_COMMAND)

    # ------------------------------------------------------------------ ground truth
    def _latch(self, levels: np.ndarray, brightness: int) -> None:
        self._history.append(ShownState(self._clock(), levels, int(brightness)))
        self._latch_count += 1

    def _status(self) -> P.Status:
        shown = self._history.last()
        return P.Status(
            latch_count=self._latch_count,
            shown_crc=P.state_crc(shown.levels, shown.brightness),
            rx_crc_errors=self.stats.crc_errors,
            duplicates=self.stats.duplicates,
        )

    def led_state(self) -> tuple[np.ndarray, float]:
        """What the LEDs show now: drive (L, 3) float32 in [0, 1] and brightness in [0, 1]."""
        s = self._history.last()
        return s.levels.astype(np.float32) / 255.0, s.brightness / 255.0

    def history(self) -> list[ShownState]:
        """Every latched state since start, oldest first (the first is all-off at start)."""
        return self._history.all()

    def states_during(self, t0: float, t1: float) -> list[ShownState]:
        """The states shown at any instant of the closed interval [t0, t1] (clock seconds)."""
        return self._history.during(t0, t1)


class RingEmulator:
    """The ring MCU, emulated behind a pseudo-terminal.

    A :class:`RingDevice` serves the protocol; this class gives it a pty, a serving thread, an
    inter-byte timeout (the device drops a partial frame when the line stays idle for
    :attr:`FRAME_GAP_S`, NAKs it and rescans the bytes it held) and the fault injection of
    the module docstring.

    Parameters
    ----------
    led_count : int
        LEDs on the ring (24 for IrisTac).
    version : int
        Protocol version reported by HELLO (change it to test the host's version check).
    faults : FaultSpec
        Fault injection (none by default).
    baudrate : float or None
        When set, model the UART's time on the wire for every frame in both directions.
    seed : int
        Seed of the fault injector's random generator (faults are reproducible).
    firmware : str
        Firmware identifier reported by HELLO.
    """

    FRAME_GAP_S = RingDevice.FRAME_GAP_S

    def __init__(
        self,
        led_count: int = 24,
        *,
        version: int = P.PROTOCOL_VERSION,
        faults: FaultSpec | None = None,
        baudrate: float | None = None,
        seed: int = 0,
        firmware: str = "iristac-ring-emulator/1",
    ) -> None:
        self.led_count = led_count
        self.version = version
        self.faults = faults or FaultSpec()
        self.baudrate = baudrate
        self.firmware = firmware
        self.stats = EmulatorStats()
        self._rng = random.Random(seed)
        self.device = RingDevice(led_count, version=version, firmware=firmware, send=self._send,
                                 frame_gap_s=self._frame_gap(), stats=self.stats)
        # With faults or a wire-time model the host's bytes are split into frames before they
        # cross the wire (faults act on whole frames); otherwise they reach the device as sent.
        self._wire = P.FrameParser() if (self.faults.any or baudrate) else None
        self._master: int | None = None
        self._slave: int | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.disconnected = threading.Event()
        self.path: str | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> str:
        """Open the pty and start serving; return the device path for the host to open."""
        if self._thread is not None:
            return self.path  # type: ignore[return-value]
        master, slave = os.openpty()
        # Raw mode: no echo, no newline translation; pyserial sets this too, but the emulator
        # must not depend on the host doing so.
        tty.setraw(slave)
        self._master, self._slave = master, slave
        self.path = os.ttyname(slave)
        self._thread = threading.Thread(target=self._serve, name="ring-emulator", daemon=True)
        self._thread.start()
        return self.path

    def stop(self) -> None:
        """Stop serving and close the pty (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close_fds()

    def __enter__(self) -> RingEmulator:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the emulator stops (disconnect or :meth:`stop`); True if it did."""
        if self._thread is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _close_fds(self) -> None:
        for name in ("_master", "_slave"):
            fd = getattr(self, name)
            if fd is not None:
                setattr(self, name, None)
                try:
                    os.close(fd)
                except OSError:
                    pass

    # ------------------------------------------------------------------ ground truth
    def led_state(self) -> tuple[np.ndarray, float]:
        """What the LEDs show now: drive (L, 3) float32 in [0, 1] and brightness in [0, 1]."""
        return self.device.led_state()

    def history(self) -> list[ShownState]:
        """Every latched state since start, oldest first (the first is all-off at start)."""
        return self.device.history()

    def states_during(self, t0: float, t1: float) -> list[ShownState]:
        """The states shown at any instant of the closed interval [t0, t1] (monotonic s)."""
        return self.device.states_during(t0, t1)

    # ------------------------------------------------------------------ the device loop
    def _serve(self) -> None:
        master = self._master
        device = self.device
        try:
            while not self._stop.is_set():
                # While a partial frame is buffered, wait only one frame gap for the rest, as
                # firmware does with an inter-byte timeout: a corrupted length must not make the
                # device swallow the host's retransmissions.
                gap = device.frame_gap_s if device.pending else 0.05
                ready, _, _ = select.select([master], [], [], gap)
                if not ready:
                    device.poll()
                    continue
                data = os.read(master, 4096)
                if not data:
                    break
                self.stats.bytes_in += len(data)
                if self._wire is None:
                    device.receive(data)
                    continue
                for frame in self._wire.feed(data):
                    limit = self.faults.disconnect_after
                    if limit is not None and self.stats.commands >= limit:
                        # Unplugged: the frame after the N-th command finds the device gone, so
                        # every reply to the first N has been delivered.
                        self.disconnected.set()
                        return
                    self._receive(P.encode_frame(frame))
        except OSError:
            pass  # the pty was closed under us (stop())
        finally:
            if self.disconnected.is_set():
                self._close_fds()

    def _frame_gap(self) -> float:
        """Idle time after which a partial frame is dropped: 2 ms or 20 character times."""
        if self.baudrate:
            return max(self.FRAME_GAP_S, P.wire_seconds(20, self.baudrate))
        return self.FRAME_GAP_S

    def _cross_wire(self, raw: bytes, direction: str) -> bytes | None:
        """One frame crossing the emulated wire (``direction`` "in" or "out"): maybe lost,
        maybe one bit flipped, and with the baud model its time on the line."""
        f, rng = self.faults, self._rng
        if f.drop and rng.random() < f.drop:
            setattr(self.stats, f"dropped_{direction}", getattr(self.stats, f"dropped_{direction}") + 1)
            return None
        if f.corrupt and rng.random() < f.corrupt:
            raw = _flip_bit(raw, rng)
            setattr(self.stats, f"corrupted_{direction}",
                    getattr(self.stats, f"corrupted_{direction}") + 1)
        if self.baudrate:
            time.sleep(P.wire_seconds(len(raw), self.baudrate))
        return raw

    def _receive(self, raw: bytes) -> None:
        arrived = self._cross_wire(raw, "in")
        if arrived is None:
            return
        f = self.faults
        if f.delay and self._rng.random() < f.delay:
            self.stats.delayed += 1
            time.sleep(f.delay_s)
        self.device.receive(arrived)

    def _send(self, raw: bytes) -> None:
        sent = self._cross_wire(raw, "out") if self._wire is not None else raw
        if sent is None:
            return
        self.stats.bytes_out += len(sent)
        os.write(self._master, sent)  # type: ignore[arg-type]


def _flip_bit(raw: bytes, rng: random.Random) -> bytes:
    out = bytearray(raw)
    i = rng.randrange(len(out))
    out[i] ^= 1 << rng.randrange(8)
    return bytes(out)


def serve_forever(
    *,
    led_count: int = 24,
    faults: FaultSpec | None = None,
    baudrate: float | None = None,
    version: int | None = None,
    seed: int = 0,
    duration: float | None = None,
    announce=print,
) -> int:
    """Run an emulator until Ctrl-C, ``duration`` or a fault-injected disconnect.

    Prints the device path first (flushed, on its own line), so a script can read it.
    Returns 0, or 1 after an injected disconnect.
    """
    emu = RingEmulator(
        led_count,
        version=P.PROTOCOL_VERSION if version is None else version,
        faults=faults,
        baudrate=baudrate,
        seed=seed,
    )
    path = emu.start()
    announce(path, flush=True)
    try:
        emu.wait(duration)
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    if emu.disconnected.is_set():
        import sys

        print(f"emulated ring disconnected after {emu.stats.commands} commands", file=sys.stderr)
        return 1
    return 0
