"""Host client for the LED ring over pyserial: retries, backoff, duplicate replies, clear errors.

Every command is one request/reply exchange identified by a sequence number. The client
retransmits the *same* frame (same sequence number) on a timeout, on a corrupted reply and on a
``NAK BAD_CRC``; the device answers a retransmission from its reply cache without executing it
again, so retries are safe for every command. Replies whose sequence number is not the one
awaited (a late reply to an earlier attempt, a duplicate ACK) are counted and ignored.

After SHOW the device reports the CRC-16 of the state it latched; the client compares it with
the state it sent, so a pattern is only reported as shown when the ring confirms it.

Examples
--------
>>> from pipeline.capture.emulator import RingEmulator
>>> with RingEmulator(led_count=4) as emu, RingClient(emu.path, timeout=0.2) as ring:
...     print(ring.info.led_count, ring.info.version)
...     status = ring.show_pattern(np.full((4, 3), 0.5), 1.0)
...     print(status.latch_count, ring.stats.retries)
4 1
1 0
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
import serial
import serial.tools.list_ports

from pipeline.base.errors import UserError
from pipeline.capture import protocol as P

__all__ = [
    "RingError",
    "RingPortError",
    "RingTimeout",
    "RingProtocolError",
    "RingDisconnected",
    "ClientStats",
    "RingClient",
    "available_ports",
]


class RingError(UserError):
    """Any failure talking to the ring (the CLI prints it as one line)."""


class RingPortError(RingError):
    """The serial port does not exist or cannot be opened."""


class RingTimeout(RingError):
    """The device did not answer a command after every retry."""


class RingProtocolError(RingError):
    """The device answered, but not as this host expects (version, refusal, wrong state)."""


class RingDisconnected(RingError):
    """The serial device went away (unplugged) in the middle of a session."""


def available_ports() -> list[str]:
    """Device paths of the serial ports that ``serial.tools.list_ports`` finds."""
    return sorted(p.device for p in serial.tools.list_ports.comports())


def _ports_hint() -> str:
    ports = available_ports()
    listed = ", ".join(ports) if ports else "none found"
    return f"serial ports on this machine: {listed} (or run `iristac emulate-ring`)"


@dataclass
class ClientStats:
    """What the client had to do to get its commands through."""

    commands: int = 0
    retries: int = 0
    timeouts: int = 0
    crc_errors: int = 0
    naks: int = 0
    stale_replies: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0


class RingClient:
    """Talk to the LED ring on a serial port.

    Parameters
    ----------
    port : str
        Serial device path (``/dev/ttyACM0``, ``COM3``, an emulator's ``/dev/pts/N``) or a
        pyserial URL (``loop://``, ``socket://host:port``).
    baudrate : int
        UART speed; the emulator ignores it unless it models wire time.
    timeout : float
        Seconds to wait for the first reply to a command; later attempts wait longer.
    retries : int
        Retransmissions per command before :class:`RingTimeout`.
    backoff : float
        Factor applied to the timeout after each timed-out attempt (capped at ``max_timeout``).
    max_timeout : float
        Upper bound of the per-attempt timeout in seconds.
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115200,
        timeout: float = 0.1,
        retries: int = 8,
        backoff: float = 1.5,
        max_timeout: float = 1.0,
    ) -> None:
        if timeout <= 0 or max_timeout < timeout:
            raise ValueError(f"need 0 < timeout <= max_timeout, got {timeout}, {max_timeout}")
        if retries < 0 or backoff < 1:
            raise ValueError(f"need retries >= 0 and backoff >= 1, got {retries}, {backoff}")
        self.port = port
        self.baudrate = baudrate
        self.timeout = timeout
        self.retries = retries
        self.backoff = backoff
        self.max_timeout = max_timeout
        self.stats = ClientStats()
        self.info: P.Hello | None = None
        self._serial: serial.Serial | None = None
        self._parser = P.FrameParser()
        self._seq = 0
        self._expected: tuple[np.ndarray, int] | None = None

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> P.Hello:
        """Open the port and do the version handshake; return the device's HELLO reply.

        Raises
        ------
        RingPortError
            The port does not exist or cannot be opened (the message lists the ports found).
        RingTimeout
            Nothing answered HELLO (wrong port or wrong baud rate).
        RingProtocolError
            The device speaks another protocol version.
        """
        if "://" not in self.port and not os.path.exists(self.port):
            raise RingPortError(f"serial port {self.port!r} does not exist; {_ports_hint()}")
        try:
            self._serial = serial.serial_for_url(
                self.port, baudrate=self.baudrate, timeout=self.timeout, write_timeout=1.0
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise RingPortError(f"cannot open serial port {self.port!r}: {exc}; {_ports_hint()}") from None
        self._serial.reset_input_buffer()
        self._parser.reset()
        try:
            hello = self.hello()
        except RingTimeout:
            self.close()
            raise RingTimeout(
                f"no IrisTac ring answered HELLO on {self.port!r} at {self.baudrate} baud after "
                f"{self.retries + 1} attempts; is this the ring's port? {_ports_hint()}"
            ) from None
        except RingError:
            self.close()
            raise
        if hello.version != P.PROTOCOL_VERSION:
            self.close()
            raise RingProtocolError(
                f"the ring on {self.port!r} (firmware {hello.firmware!r}) speaks ring protocol "
                f"version {hello.version}, this host speaks version {P.PROTOCOL_VERSION}: update "
                "the ring firmware or the iristac software so they match"
            )
        self.info = hello
        return hello

    def close(self) -> None:
        """Close the port (idempotent)."""
        if self._serial is not None:
            try:
                self._serial.close()
            except (serial.SerialException, OSError):
                pass
            self._serial = None

    def __enter__(self) -> RingClient:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ commands
    def hello(self) -> P.Hello:
        """HELLO: the device's protocol version, LED count and firmware."""
        data = self.transact(P.Command.HELLO, bytes((P.PROTOCOL_VERSION,)))
        try:
            return P.decode_hello(data)
        except ValueError as exc:
            raise RingProtocolError(f"bad HELLO reply from {self.port!r}: {exc}") from None

    def set_all(self, drive: np.ndarray, brightness: float) -> None:
        """SET_ALL: load the drive (L, 3) in [0, 1] and brightness in [0, 1] (not shown yet)."""
        levels, level_b = P.quantize_state(drive, brightness)
        self._check_led_count(levels.shape[0])
        self.transact(P.Command.SET_ALL, P.state_payload(levels, level_b))
        self._expected = (levels, level_b)

    def set_one(self, index: int, rgb: tuple[float, float, float]) -> None:
        """SET_ONE: load one LED's RGB drive in [0, 1] (not shown yet)."""
        levels, _ = P.quantize_state(np.asarray(rgb, dtype=np.float64).reshape(1, 3), 0.0)
        self.transact(P.Command.SET_ONE, bytes((index,)) + levels.tobytes())
        if self._expected is not None:
            self._expected[0][index] = levels[0]

    def show(self) -> P.Status:
        """SHOW: latch the loaded state; verify the device latched what this client sent."""
        status = self._status_reply(self.transact(P.Command.SHOW))
        if self._expected is not None:
            want = P.state_crc(*self._expected)
            if status.shown_crc != want:
                raise RingProtocolError(
                    f"the ring on {self.port!r} shows a state with CRC {status.shown_crc:#06x}, "
                    f"but the state sent has CRC {want:#06x} (was the ring reset?)"
                )
        return status

    def off(self) -> P.Status:
        """OFF: turn every LED off at once (also clears the loaded state)."""
        status = self._status_reply(self.transact(P.Command.OFF))
        if self.info is not None:
            self._expected = (np.zeros((self.info.led_count, 3), np.uint8), 0)
        return status

    def status(self) -> P.Status:
        """STATUS: latch counter, CRC of the shown state and the device's error counters."""
        return self._status_reply(self.transact(P.Command.STATUS))

    def show_pattern(self, drive: np.ndarray, brightness: float) -> P.Status:
        """SET_ALL then SHOW; returns once the ring has confirmed the pattern is shown."""
        self.set_all(drive, brightness)
        return self.show()

    # ------------------------------------------------------------------ the exchange
    def transact(self, cmd: P.Command, payload: bytes = b"") -> bytes:
        """Send one command and return its ACK data (the bytes after the command echo).

        Retransmits the same frame on timeouts (with backoff), corrupted replies and
        ``NAK BAD_CRC``/``BUSY``; raises :class:`RingTimeout` after ``retries`` retransmissions,
        :class:`RingProtocolError` when the device refuses the command, and
        :class:`RingDisconnected` when the port goes away.
        """
        if self._serial is None:
            raise RingError(f"the ring on {self.port!r} is not open")
        # Sequence numbers run 1..255; 0 is reserved for the device's NAK BAD_CRC.
        self._seq = self._seq % 255 + 1
        seq = self._seq
        raw = P.encode_frame(P.Frame(seq, cmd, payload))
        self.stats.commands += 1
        timeout = self.timeout
        for attempt in range(self.retries + 1):
            if attempt:
                self.stats.retries += 1
            self._write(raw, cmd, seq)
            outcome, data = self._await(seq, cmd, time.monotonic() + timeout)
            if outcome == "ack":
                return data
            if outcome == "timeout":
                self.stats.timeouts += 1
                timeout = min(timeout * self.backoff, self.max_timeout)
            elif outcome == "nak":
                code = data[0]
                if code == P.NakCode.BUSY:
                    time.sleep(min(timeout, self.max_timeout))
                elif code != P.NakCode.BAD_CRC:
                    raise RingProtocolError(
                        f"the ring on {self.port!r} refused {P.Command(cmd).name} (seq {seq}): "
                        f"{_nak_name(code)}"
                    )
            # "resend": a corrupted reply or NAK BAD_CRC; retransmit at once.
        raise RingTimeout(
            f"no valid reply from the ring on {self.port!r} to {P.Command(cmd).name} (seq {seq}) "
            f"after {self.retries + 1} attempts"
        )

    def _write(self, raw: bytes, cmd: P.Command, seq: int) -> None:
        try:
            self._serial.write(raw)  # type: ignore[union-attr]
        except (serial.SerialException, OSError) as exc:
            raise self._disconnected(cmd, seq, exc) from None
        self.stats.bytes_sent += len(raw)

    def _await(self, seq: int, cmd: P.Command, deadline: float) -> tuple[str, bytes]:
        ser = self._serial
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                # Nothing more is coming: a buffered partial frame is bogus (corrupted length);
                # rescan its bytes, which may hold the reply itself.
                outcome = self._match(self._parser.resync(), seq, cmd)
                return outcome if outcome is not None else ("timeout", b"")
            try:
                ser.timeout = remaining  # type: ignore[union-attr]
                data = ser.read(max(1, ser.in_waiting))  # type: ignore[union-attr]
            except (serial.SerialException, OSError) as exc:
                raise self._disconnected(cmd, seq, exc) from None
            if not data:
                continue
            self.stats.bytes_received += len(data)
            crc_before = self._parser.crc_errors
            frames = self._parser.feed(data)
            corrupted = self._parser.crc_errors != crc_before
            self.stats.crc_errors += self._parser.crc_errors - crc_before
            outcome = self._match(frames, seq, cmd)
            if outcome is not None:
                return outcome
            if corrupted:
                return "resend", b""

    def _match(self, frames: list[P.Frame], seq: int, cmd: P.Command) -> tuple[str, bytes] | None:
        """The outcome decided by these received frames, or None to keep waiting."""
        for frame in frames:
            if frame.cmd == P.Command.NAK and frame.seq == 0 and frame.payload[1:2] == bytes(
                (P.NakCode.BAD_CRC,)
            ):
                self.stats.naks += 1
                return "nak", bytes((P.NakCode.BAD_CRC,))
            echoed = frame.payload[:1] == bytes((cmd,))
            if frame.seq != seq or not echoed or frame.cmd not in (P.Command.ACK, P.Command.NAK):
                self.stats.stale_replies += 1  # a late or duplicate reply to an earlier try
                continue
            if frame.cmd == P.Command.ACK:
                return "ack", frame.payload[1:]
            self.stats.naks += 1
            return "nak", frame.payload[1:2] or b"\x00"
        return None

    def _disconnected(self, cmd: P.Command, seq: int, exc: Exception) -> RingDisconnected:
        self.close()
        return RingDisconnected(
            f"the ring on {self.port!r} disconnected during {P.Command(cmd).name} (seq {seq}): "
            f"{exc}"
        )

    def _status_reply(self, data: bytes) -> P.Status:
        try:
            return P.decode_status(data)
        except ValueError as exc:
            raise RingProtocolError(f"bad status reply from {self.port!r}: {exc}") from None

    def _check_led_count(self, n: int) -> None:
        if self.info is not None and n != self.info.led_count:
            raise RingProtocolError(
                f"pattern has {n} LEDs but the ring on {self.port!r} has {self.info.led_count}"
            )


def _nak_name(code: int) -> str:
    try:
        return P.NakCode(code).name
    except ValueError:
        return f"unknown NAK code {code:#04x}"
