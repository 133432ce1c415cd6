"""The IrisTac ring protocol: framing, CRC-16, commands, and a streaming parser that resyncs.

The wire format is specified in ``docs/ring-protocol.md``; this module is its reference
implementation, shared by the host client and the MCU emulator so the two can never drift.

A frame is::

    START(0xA5) LEN SEQ CMD PAYLOAD[LEN] CRC16_LO CRC16_HI

with the CRC-16/CCITT-FALSE checksum (poly 0x1021, init 0xFFFF) over ``LEN SEQ CMD PAYLOAD``.

Examples
--------
>>> raw = encode_frame(Frame(seq=7, cmd=Command.SHOW))
>>> raw.hex(" ")
'a5 00 07 04 8f 15'
>>> parser = FrameParser()
>>> parser.feed(b"\\x00garbage" + raw)
[Frame(seq=7, cmd=<Command.SHOW: 4>, payload=b'')]
>>> crc16(b"123456789") == 0x29B1   # the standard check value of CRC-16/CCITT-FALSE
True
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

import numpy as np

__all__ = [
    "PROTOCOL_VERSION",
    "START",
    "MAX_PAYLOAD",
    "HEADER_SIZE",
    "OVERHEAD",
    "Command",
    "NakCode",
    "Frame",
    "crc16",
    "encode_frame",
    "FrameParser",
    "quantize_state",
    "state_payload",
    "parse_state_payload",
    "state_crc",
    "Hello",
    "Status",
    "decode_hello",
    "encode_hello",
    "decode_status",
    "encode_status",
    "wire_seconds",
]

PROTOCOL_VERSION = 1
START = 0xA5
# Frames longer than this are rejected at the header, so a false START in garbage never makes
# the parser wait for hundreds of bytes before it can resynchronise.
MAX_PAYLOAD = 200
HEADER_SIZE = 4  # START LEN SEQ CMD
OVERHEAD = HEADER_SIZE + 2  # header plus the CRC


class Command(enum.IntEnum):
    """Command codes (host → device) and reply codes (device → host)."""

    HELLO = 0x01
    SET_ALL = 0x02
    SET_ONE = 0x03
    SHOW = 0x04
    OFF = 0x05
    STATUS = 0x06
    ACK = 0x80
    NAK = 0x81


class NakCode(enum.IntEnum):
    """Why a device refused a frame (second payload byte of a NAK)."""

    BAD_CRC = 0x01  # a frame failed its CRC; SEQ of the NAK is 0, the host should resend
    UNKNOWN_COMMAND = 0x02
    BAD_LENGTH = 0x03
    BAD_ARGUMENT = 0x04
    BUSY = 0x05


@dataclass(frozen=True)
class Frame:
    """One decoded frame: sequence number, command code and payload bytes."""

    seq: int
    cmd: int
    payload: bytes = b""

    def __repr__(self) -> str:
        try:
            cmd = repr(Command(self.cmd))
        except ValueError:
            cmd = hex(self.cmd)
        return f"Frame(seq={self.seq}, cmd={cmd}, payload={self.payload!r})"


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF, no reflection, no xor-out).

    Parameters
    ----------
    data : bytes
        The bytes to checksum.
    crc : int
        Initial value (chain calls by passing the previous result).

    Returns
    -------
    int
        The 16-bit checksum.

    Examples
    --------
    >>> hex(crc16(b"123456789"))
    '0x29b1'
    """
    table = _CRC_TABLE
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ b) & 0xFF]
    return crc


def encode_frame(frame: Frame) -> bytes:
    """Serialise a frame to the bytes sent on the wire.

    Raises
    ------
    ValueError
        If the sequence number or command is not one byte, or the payload is too long.

    Examples
    --------
    >>> len(encode_frame(Frame(seq=1, cmd=Command.SET_ALL, payload=bytes(73))))
    79
    """
    if not 0 <= frame.seq <= 255:
        raise ValueError(f"seq must be in 0..255, got {frame.seq}")
    if not 0 <= int(frame.cmd) <= 255:
        raise ValueError(f"cmd must be in 0..255, got {frame.cmd}")
    if len(frame.payload) > MAX_PAYLOAD:
        raise ValueError(f"payload must be at most {MAX_PAYLOAD} bytes, got {len(frame.payload)}")
    body = bytes((len(frame.payload), frame.seq, int(frame.cmd))) + bytes(frame.payload)
    return bytes((START,)) + body + struct.pack("<H", crc16(body))


class FrameParser:
    """Incremental frame decoder that resynchronises after garbage.

    Feed it whatever bytes arrived; it returns the complete, CRC-valid frames found so far
    and keeps the remainder. On a false start (a START byte in garbage, an impossible length
    or a CRC mismatch) it drops only that START byte and rescans the bytes after it, so a real
    frame that was swallowed by a bogus length is still found.

    Attributes
    ----------
    crc_errors : int
        Candidate frames whose CRC did not match.
    length_errors : int
        Candidate headers whose length exceeded :data:`MAX_PAYLOAD`.
    skipped_bytes : int
        Bytes discarded while searching for a START byte.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.crc_errors = 0
        self.length_errors = 0
        self.skipped_bytes = 0

    def reset(self) -> None:
        """Forget any partial frame (e.g. after the line was reopened)."""
        self._buf.clear()

    @property
    def pending(self) -> int:
        """Bytes buffered that are not yet part of a complete frame."""
        return len(self._buf)

    def resync(self) -> list[Frame]:
        """Declare the line idle: any partial frame is bogus, so drop its START and rescan.

        A receiver calls this when no byte arrived for longer than a frame gap while bytes
        are still buffered (a corrupted length made the parser wait for bytes that will never
        come). Returns any valid frames found in the buffered bytes; the buffer ends empty.

        Examples
        --------
        >>> p = FrameParser()
        >>> good = encode_frame(Frame(seq=3, cmd=Command.OFF))
        >>> p.feed(bytes((START, 150)) + good)   # a false START whose length swallows `good`
        []
        >>> p.resync()
        [Frame(seq=3, cmd=<Command.OFF: 5>, payload=b'')]
        """
        return list(self.iter_resync())

    def iter_resync(self):
        """:meth:`resync` as a generator: frames one at a time, the error counters updated
        as the scan reaches each dropped candidate (a device answers each frame before the
        scan goes on, as the byte-wise C parser does)."""
        while self._buf:
            self.skipped_bytes += 1
            del self._buf[:1]
            yield from self.iter_feed(b"")

    def feed(self, data: bytes) -> list[Frame]:
        """Add received bytes; return the complete valid frames, oldest first."""
        return list(self.iter_feed(data))

    def iter_feed(self, data: bytes):
        """:meth:`feed` as a generator: each frame is yielded as soon as the scan finds it, so
        the counters read between frames count only the candidates dropped before it."""
        buf = self._buf
        buf.extend(data)
        while True:
            start = buf.find(START)
            if start < 0:
                self.skipped_bytes += len(buf)
                buf.clear()
                return
            if start:
                self.skipped_bytes += start
                del buf[:start]
            if len(buf) < HEADER_SIZE:
                return
            length = buf[1]
            if length > MAX_PAYLOAD:
                self.length_errors += 1
                self.skipped_bytes += 1
                del buf[:1]
                continue
            total = HEADER_SIZE + length + 2
            if len(buf) < total:
                return
            body = bytes(buf[1 : HEADER_SIZE + length])
            (crc,) = struct.unpack_from("<H", buf, HEADER_SIZE + length)
            if crc16(body) != crc:
                self.crc_errors += 1
                self.skipped_bytes += 1
                del buf[:1]
                continue
            del buf[:total]
            yield Frame(seq=body[1], cmd=body[2], payload=body[3:])


def quantize_state(drive: np.ndarray, brightness: float) -> tuple[np.ndarray, int]:
    """Quantise an LED drive matrix and brightness to the 8-bit levels sent on the wire.

    Parameters
    ----------
    drive : ndarray, shape (L, 3)
        RGB drive per LED in [0, 1].
    brightness : float
        Global brightness in [0, 1].

    Returns
    -------
    levels : ndarray, shape (L, 3), uint8
    brightness_level : int
        In 0..255.

    Examples
    --------
    >>> levels, b = quantize_state(np.array([[1.0, 0.5, 0.0]]), 0.25)
    >>> levels.tolist(), b
    ([[255, 128, 0]], 64)
    """
    drive = np.asarray(drive, dtype=np.float64)
    if drive.ndim != 2 or drive.shape[1] != 3:
        raise ValueError(f"drive must have shape (L, 3), got {drive.shape}")
    if not np.all(np.isfinite(drive)) or drive.min(initial=0) < 0 or drive.max(initial=0) > 1:
        raise ValueError("drive values must be finite and in [0, 1]")
    if not (np.isfinite(brightness) and 0 <= brightness <= 1):
        raise ValueError(f"brightness must be in [0, 1], got {brightness}")
    # floor(x*255 + 0.5): round half up, identical on host and firmware.
    levels = np.floor(drive * 255 + 0.5).astype(np.uint8)
    return levels, int(np.floor(brightness * 255 + 0.5))


def state_payload(levels: np.ndarray, brightness_level: int) -> bytes:
    """The SET_ALL payload: L × (R, G, B) bytes, LED 0 first, then the brightness byte."""
    levels = np.asarray(levels)
    if levels.ndim != 2 or levels.shape[1] != 3 or levels.dtype != np.uint8:
        raise ValueError(f"levels must be uint8 of shape (L, 3), got {levels.dtype} {levels.shape}")
    if not 0 <= brightness_level <= 255:
        raise ValueError(f"brightness level must be in 0..255, got {brightness_level}")
    return levels.tobytes() + bytes((brightness_level,))


def parse_state_payload(payload: bytes, led_count: int) -> tuple[np.ndarray, int]:
    """Inverse of :func:`state_payload`; raises ValueError on a wrong length."""
    if len(payload) != 3 * led_count + 1:
        raise ValueError(f"SET_ALL payload must be {3 * led_count + 1} bytes, got {len(payload)}")
    levels = np.frombuffer(payload[:-1], dtype=np.uint8).reshape(led_count, 3).copy()
    return levels, payload[-1]


def state_crc(levels: np.ndarray, brightness_level: int) -> int:
    """CRC-16 of the shown state (what SHOW and STATUS report, so the host can verify it)."""
    return crc16(state_payload(levels, brightness_level))


@dataclass(frozen=True)
class Hello:
    """Reply to HELLO: the device's protocol version, LED count and firmware identifier."""

    version: int
    led_count: int
    firmware: str


def encode_hello(h: Hello) -> bytes:
    """Payload of the HELLO reply (after the ACK's command byte)."""
    return bytes((h.version, h.led_count)) + h.firmware.encode("ascii")[:32]


def decode_hello(data: bytes) -> Hello:
    """Inverse of :func:`encode_hello`; raises ValueError when too short."""
    if len(data) < 2:
        raise ValueError(f"HELLO reply needs at least 2 bytes, got {len(data)}")
    return Hello(version=data[0], led_count=data[1], firmware=data[2:].decode("ascii", "replace"))


@dataclass(frozen=True)
class Status:
    """Reply to STATUS (and to SHOW/OFF): what the LEDs show now and the error counters."""

    latch_count: int  # SHOW/OFF latches since power-on
    shown_crc: int  # state_crc of the shown state
    rx_crc_errors: int  # frames the device dropped for a bad CRC
    duplicates: int  # retransmissions it answered from its reply cache


_STATUS = struct.Struct("<IHHH")


def encode_status(s: Status) -> bytes:
    """Payload of the STATUS/SHOW/OFF reply (after the ACK's command byte)."""
    return _STATUS.pack(
        s.latch_count & 0xFFFFFFFF, s.shown_crc, s.rx_crc_errors & 0xFFFF, s.duplicates & 0xFFFF
    )


def decode_status(data: bytes) -> Status:
    """Inverse of :func:`encode_status`; raises ValueError on a wrong length."""
    if len(data) != _STATUS.size:
        raise ValueError(f"STATUS reply must be {_STATUS.size} bytes, got {len(data)}")
    return Status(*_STATUS.unpack(data))


def wire_seconds(n_bytes: int, baudrate: float) -> float:
    """Time ``n_bytes`` take on a UART line at ``baudrate`` (8N1: 10 bits per byte).

    >>> round(wire_seconds(79, 115200) * 1000, 2)
    6.86
    """
    return n_bytes * 10.0 / baudrate
