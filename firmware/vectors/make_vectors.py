"""Write ``protocol.vec``, the ring protocol's conformance vectors (frames in, frames out).

The vector file is the one source of truth that the C firmware's unit tests
(``make -C firmware host test``) and the Python emulator's tests read; this script is only how
it is written, so that each case says in words what it checks and every expected reply is
spelled out from docs/ring-protocol.md (framing and CRC come from
``pipeline.capture.protocol``; no device code runs here). A test checks that the committed
file is what this script writes.

    python firmware/vectors/make_vectors.py            # rewrite protocol.vec
    python firmware/vectors/make_vectors.py --check    # exit 1 if protocol.vec is stale
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from pipeline.capture import protocol as P  # noqa: E402

OUT = HERE / "protocol.vec"
C = P.Command
N = P.NakCode
LEDS = 24
FIRMWARE = "vectors"

HEADER = """\
# IrisTac LED-ring protocol, version 1: conformance vectors (frames in, frames out).
# Written by make_vectors.py (do not edit by hand); read by firmware/host/vector_runner.c
# (make -C firmware host test) and by the Python emulator's tests, so the C firmware and
# pipeline.capture.emulator.RingDevice cannot drift apart.  Spec: docs/ring-protocol.md.
#
# One directive per line; '#' starts a comment.  HEX is bytes in hex, spaces and '|'
# (between frames) ignored.
#   case NAME            a new case: a fresh device at power-on, its clock at 0 ms
#   device KEY=V ...     (optional, right after case) leds=N version=V firmware=ID
#                        (defaults: leds=24 version=1 firmware=vectors)
#   send HEX             the host sends these bytes; the device processes all of them
#   wait MS              the line stays idle MS more milliseconds (the device polls)
#   expect [HEX]         the device sent exactly these bytes since the previous expect
#                        (nothing at all when HEX is empty)
#   shown HEX            the LEDs show this state, laid out as a SET_ALL payload
#                        (L x R G B, LED 0 first, then the brightness byte)
# Frame-gap timing: the device drops a partial frame once the line was idle for MORE than
# its 2 ms frame gap; vectors only use idle times of 1 ms (too short) and 3 ms or more.
"""


def frame(seq: int, cmd: int, payload: bytes = b"") -> bytes:
    return P.encode_frame(P.Frame(seq, cmd, bytes(payload)))


def ack(seq: int, cmd: int, data: bytes = b"") -> bytes:
    return frame(seq, C.ACK, bytes((cmd,)) + data)


def nak(seq: int, cmd: int, code: int) -> bytes:
    return frame(seq, C.NAK, bytes((cmd, code)))


NAK_CRC = frame(0, C.NAK, bytes((0, N.BAD_CRC)))  # a frame was dropped: resend


def status(latches: int, state: bytes, rx_errors: int = 0, duplicates: int = 0) -> bytes:
    return struct.pack("<IHHH", latches, P.crc16(state), rx_errors, duplicates)


def state(levels: bytes, brightness: int) -> bytes:
    return bytes(levels) + bytes((brightness,))


def hello_data(version: int = 1, leds: int = LEDS, firmware: str = FIRMWARE) -> bytes:
    return bytes((version, leds)) + firmware.encode("ascii")[:32]


def levels(seed: int, leds: int = LEDS, avoid_start: bool = True) -> bytes:
    """Deterministic pseudo-random LED levels (an LCG; no 0xA5 byte unless asked)."""
    out, x = bytearray(), seed
    while len(out) < 3 * leds:
        x = (1103515245 * x + 12345) % 2**31
        b = (x >> 16) & 0xFF
        if avoid_start and b == P.START:
            continue
        out.append(b)
    return bytes(out)


def flip(raw: bytes, byte: int, bit: int) -> bytes:
    out = bytearray(raw)
    out[byte] ^= 1 << bit
    return bytes(out)


OFF = state(bytes(3 * LEDS), 0)


class Writer:
    def __init__(self) -> None:
        self.lines = [HEADER]
        self.cases = 0

    def case(self, name: str, why: str, **device) -> None:
        self.cases += 1
        self.lines.append("")
        self.lines.append(f"# {why}")
        self.lines.append(f"case {name}")
        if device:
            self.lines.append("device " + " ".join(f"{k}={v}" for k, v in device.items()))

    def send(self, *parts: bytes, note: str = "") -> None:
        self._emit("send", parts, note)

    def expect(self, *parts: bytes, note: str = "") -> None:
        self._emit("expect", parts, note)

    def wait(self, ms: int) -> None:
        self.lines.append(f"wait {ms}")

    def shown(self, s: bytes) -> None:
        self._emit("shown", (s,), "")

    def _emit(self, word: str, parts, note: str) -> None:
        text = " | ".join(p.hex(" ").upper() for p in parts if p)
        line = f"{word} {text}".rstrip()
        self.lines.append(line + (f"  # {note}" if note else ""))

    def text(self) -> str:
        return "\n".join(self.lines) + "\n"


def build() -> Writer:
    w = Writer()
    a, b = levels(1), levels(2)
    sa, sb = state(a, 200), state(b, 17)

    # --- the spec's own example, typed by hand ---------------------------------------------
    example = bytes.fromhex("A5 00 07 04 8F 15")
    assert example == frame(7, C.SHOW), "the spec's SHOW example disagrees with the encoder"
    w.case("spec-example", "docs/ring-protocol.md: SHOW with SEQ 7 is A5 00 07 04 8F 15.")
    w.send(example)
    w.expect(ack(7, C.SHOW, status(1, OFF)))

    # --- handshake and versions -------------------------------------------------------
    w.case("power-on", "At power-on nothing is latched and the LEDs are off.")
    w.shown(OFF)
    w.send(frame(1, C.STATUS))
    w.expect(ack(1, C.STATUS, status(0, OFF)))

    w.case("hello", "HELLO: the device's version, LED count and firmware id.")
    w.send(frame(1, C.HELLO, b"\x01"))
    w.expect(ack(1, C.HELLO, hello_data()))

    w.case("hello-newer-host", "A host of another version still learns the device's version.")
    w.send(frame(1, C.HELLO, b"\x02"))
    w.expect(ack(1, C.HELLO, hello_data()))

    w.case("hello-empty-payload", "HELLO is answered whatever its payload.")
    w.send(frame(9, C.HELLO))
    w.expect(ack(9, C.HELLO, hello_data()))

    w.case("hello-device-version-2", "A device of version 2 says so (the host reports the mismatch).",
           version=2)
    w.send(frame(1, C.HELLO, b"\x01"))
    w.expect(ack(1, C.HELLO, hello_data(version=2)))

    long_id = "iristac-ring-with-a-very-long-firmware-id-x"
    w.case("hello-long-firmware-id", "Only the first 32 bytes of the firmware id are sent.",
           firmware=long_id)
    w.send(frame(1, C.HELLO, b"\x01"))
    w.expect(ack(1, C.HELLO, hello_data(firmware=long_id[:32])))

    # --- set LEDs, brightness, SHOW ----------------------------------------------------
    w.case("set-all-then-show", "SET_ALL loads without showing; SHOW latches it and reports "
           "the CRC of the latched state.")
    w.send(frame(1, C.SET_ALL, sa))
    w.expect(ack(1, C.SET_ALL))
    w.shown(OFF)
    w.send(frame(2, C.STATUS))
    w.expect(ack(2, C.STATUS, status(0, OFF)))
    w.send(frame(3, C.SHOW))
    w.expect(ack(3, C.SHOW, status(1, sa)))
    w.shown(sa)

    w.case("brightness", "The brightness byte of SET_ALL is part of the state (and its CRC).")
    w.send(frame(1, C.SET_ALL, sa), frame(2, C.SHOW))
    w.expect(ack(1, C.SET_ALL), ack(2, C.SHOW, status(1, sa)))
    dim = state(a, 1)
    w.send(frame(3, C.SET_ALL, dim), frame(4, C.SHOW))
    w.expect(ack(3, C.SET_ALL), ack(4, C.SHOW, status(2, dim)))
    w.shown(dim)

    w.case("set-all-bad-length", "SET_ALL must carry 3L + 1 bytes.")
    w.send(frame(1, C.SET_ALL, sa[:-1]))
    w.expect(nak(1, C.SET_ALL, N.BAD_LENGTH))
    w.send(frame(2, C.SET_ALL, sa + b"\x00"))
    w.expect(nak(2, C.SET_ALL, N.BAD_LENGTH))
    w.send(frame(3, C.SHOW))
    w.expect(ack(3, C.SHOW, status(1, OFF)), note="nothing was loaded")

    six = state(levels(3, leds=6), 255)
    w.case("six-leds", "A ring of 6 LEDs takes 19-byte SET_ALLs only.", leds=6)
    w.send(frame(1, C.HELLO, b"\x01"))
    w.expect(ack(1, C.HELLO, hello_data(leds=6)))
    w.send(frame(2, C.SET_ALL, sa))
    w.expect(nak(2, C.SET_ALL, N.BAD_LENGTH))
    w.send(frame(3, C.SET_ALL, six), frame(4, C.SHOW))
    w.expect(ack(3, C.SET_ALL), ack(4, C.SHOW, status(1, six)))
    w.shown(six)

    w.case("set-one", "SET_ONE loads one LED of the pending state.")
    base = state(bytes(3 * LEDS), 255)
    one = bytearray(base)
    one[15:18] = b"\x01\x02\x03"
    w.send(frame(1, C.SET_ALL, base), frame(2, C.SET_ONE, b"\x05\x01\x02\x03"))
    w.expect(ack(1, C.SET_ALL), ack(2, C.SET_ONE))
    w.shown(OFF)
    w.send(frame(3, C.SHOW))
    w.expect(ack(3, C.SHOW, status(1, bytes(one))))
    w.shown(bytes(one))

    w.case("set-one-last-led-and-bad-index", "Index L - 1 is the last LED; L and above are "
           "BAD_ARGUMENT.")
    last = bytearray(OFF)
    last[69:72] = b"\xff\x00\x80"
    w.send(frame(1, C.SET_ONE, b"\x17\xff\x00\x80"))
    w.expect(ack(1, C.SET_ONE))
    w.send(frame(2, C.SET_ONE, b"\x18\x01\x01\x01"))
    w.expect(nak(2, C.SET_ONE, N.BAD_ARGUMENT))
    w.send(frame(3, C.SET_ONE, b"\xff\x01\x01\x01"))
    w.expect(nak(3, C.SET_ONE, N.BAD_ARGUMENT))
    w.send(frame(4, C.SHOW))
    w.expect(ack(4, C.SHOW, status(1, bytes(last))))

    w.case("set-one-bad-length", "SET_ONE must carry 4 bytes.")
    w.send(frame(1, C.SET_ONE, b"\x00\x01\x02"))
    w.expect(nak(1, C.SET_ONE, N.BAD_LENGTH))
    w.send(frame(2, C.SET_ONE, b"\x00\x01\x02\x03\x04"))
    w.expect(nak(2, C.SET_ONE, N.BAD_LENGTH))

    w.case("show-twice", "Every SHOW (with a new SEQ) is one more latch.")
    w.send(frame(1, C.SET_ALL, sb), frame(2, C.SHOW), frame(3, C.SHOW))
    w.expect(ack(1, C.SET_ALL), ack(2, C.SHOW, status(1, sb)), ack(3, C.SHOW, status(2, sb)))

    w.case("show-with-payload", "SHOW takes no payload: BAD_LENGTH and no latch.")
    w.send(frame(1, C.SET_ALL, sa))
    w.expect(ack(1, C.SET_ALL))
    w.send(frame(2, C.SHOW, b"\x00"))
    w.expect(nak(2, C.SHOW, N.BAD_LENGTH))
    w.shown(OFF)
    w.send(frame(3, C.STATUS))
    w.expect(ack(3, C.STATUS, status(0, OFF)))

    # --- OFF and STATUS --------------------------------------------------------------
    w.case("off", "OFF latches all-off at once and clears the pending state too.")
    w.send(frame(1, C.SET_ALL, sa), frame(2, C.SHOW))
    w.expect(ack(1, C.SET_ALL), ack(2, C.SHOW, status(1, sa)))
    w.send(frame(3, C.OFF))
    w.expect(ack(3, C.OFF, status(2, OFF)))
    w.shown(OFF)
    w.send(frame(4, C.SHOW))
    w.expect(ack(4, C.SHOW, status(3, OFF)), note="pending was cleared")

    w.case("off-and-status-with-payload", "OFF and STATUS take no payload.")
    w.send(frame(1, C.OFF, b"\x01"))
    w.expect(nak(1, C.OFF, N.BAD_LENGTH))
    w.send(frame(2, C.STATUS, b"\x01\x02"))
    w.expect(nak(2, C.STATUS, N.BAD_LENGTH))

    w.case("unknown-commands", "Codes outside the table (a reply code too) are UNKNOWN_COMMAND.")
    w.send(frame(1, 0x07))
    w.expect(nak(1, 0x07, N.UNKNOWN_COMMAND))
    w.send(frame(2, C.ACK, b"\x04"))
    w.expect(nak(2, C.ACK, N.UNKNOWN_COMMAND))
    w.send(frame(3, 0x00))
    w.expect(nak(3, 0x00, N.UNKNOWN_COMMAND))

    w.case("max-payload", "A 200-byte payload is a valid frame (the longest there is).")
    w.send(frame(1, 0x42, bytes(range(200))))
    w.expect(nak(1, 0x42, N.UNKNOWN_COMMAND))
    w.send(frame(2, C.SET_ALL, bytes(200)))
    w.expect(nak(2, C.SET_ALL, N.BAD_LENGTH))

    # --- sequence numbers and duplicates ------------------------------------------------
    w.case("duplicate-show", "A retransmitted SHOW (same SEQ, same frame) gets the cached "
           "reply and is not executed again.")
    w.send(frame(1, C.SET_ALL, sa), frame(2, C.SHOW))
    w.expect(ack(1, C.SET_ALL), ack(2, C.SHOW, status(1, sa)))
    w.send(frame(2, C.SHOW))
    w.expect(ack(2, C.SHOW, status(1, sa)), note="the cached reply: latch_count still 1")
    w.send(frame(3, C.STATUS))
    w.expect(ack(3, C.STATUS, status(1, sa, duplicates=1)))

    w.case("duplicate-status-is-the-cached-reply", "A retransmitted STATUS re-sends the old "
           "reply (its counters as they were).")
    w.send(frame(1, C.STATUS), frame(1, C.STATUS), frame(1, C.STATUS))
    w.expect(*(ack(1, C.STATUS, status(0, OFF)),) * 3)
    w.send(frame(2, C.STATUS))
    w.expect(ack(2, C.STATUS, status(0, OFF, duplicates=2)))

    w.case("duplicate-of-a-nak", "A retransmitted refused command gets the same NAK.")
    w.send(frame(1, C.SET_ONE, b"\x30\x00\x00\x00"))
    w.expect(nak(1, C.SET_ONE, N.BAD_ARGUMENT))
    w.send(frame(1, C.SET_ONE, b"\x30\x00\x00\x00"))
    w.expect(nak(1, C.SET_ONE, N.BAD_ARGUMENT))
    w.send(frame(2, C.STATUS))
    w.expect(ack(2, C.STATUS, status(0, OFF, duplicates=1)))

    w.case("same-seq-other-payload", "Same SEQ but another payload is a new command: executed.")
    w.send(frame(1, C.SET_ALL, sa), frame(1, C.SET_ALL, sb), frame(2, C.SHOW))
    w.expect(ack(1, C.SET_ALL), ack(1, C.SET_ALL), ack(2, C.SHOW, status(1, sb)))
    w.shown(sb)

    w.case("repeat-after-another-command", "Only the last command is cached: SHOW, STATUS, then "
           "the same SHOW frame again is executed again.")
    w.send(frame(2, C.SHOW), frame(3, C.STATUS), frame(2, C.SHOW))
    w.expect(ack(2, C.SHOW, status(1, OFF)), ack(3, C.STATUS, status(1, OFF)),
             ack(2, C.SHOW, status(2, OFF)))

    w.case("seq-wrap", "SEQ 255 is followed by 1; SEQ 0 (never sent by the host) is executed too.")
    w.send(frame(255, C.SET_ALL, sb), frame(1, C.SHOW), frame(0, C.STATUS))
    w.expect(ack(255, C.SET_ALL), ack(1, C.SHOW, status(1, sb)), ack(0, C.STATUS, status(1, sb)))

    # --- CRC errors and resynchronisation -------------------------------------------------
    show5 = frame(5, C.SHOW)
    w.case("crc-error", "A frame with a bad CRC is dropped with one NAK BAD_CRC (SEQ 0); the "
           "resent frame is executed.")
    w.send(frame(1, C.SET_ALL, sa))
    w.expect(ack(1, C.SET_ALL))
    w.send(flip(show5, 5, 0))
    w.expect(NAK_CRC)
    w.send(show5)
    w.expect(ack(5, C.SHOW, status(1, sa, rx_errors=1)))

    bad_set = frame(1, C.SET_ALL, sa)
    w.case("bit-flip-in-payload", "Any flipped payload bit fails the CRC: nothing is loaded.")
    w.send(flip(bad_set, 40, 3))
    w.expect(NAK_CRC)
    w.send(frame(2, C.SHOW))
    w.expect(ack(2, C.SHOW, status(1, OFF, rx_errors=1)))

    w.case("impossible-length", "LEN > 200 is dropped at the header (NAK, counted); the bytes "
           "after its START are rescanned.")
    w.send(bytes((P.START, 201)), frame(1, C.STATUS))
    w.expect(ack(1, C.STATUS, status(0, OFF, rx_errors=1)), NAK_CRC,
             note="the frame is answered as soon as it is found; one NAK after the burst")

    w.case("garbage-without-start", "Bytes without a START are skipped silently.")
    w.send(bytes.fromhex("00 11 22 33 FF 5A 80 81"), frame(1, C.STATUS))
    w.expect(ack(1, C.STATUS, status(0, OFF)))

    w.case("false-starts-one-nak", "A burst with several false STARTs costs one NAK; each "
           "dropped candidate is counted.")
    w.send(bytes.fromhex("A5 FF A5 FE 00 A5 C9 00 11"))
    w.expect(NAK_CRC)
    w.send(frame(1, C.STATUS))
    w.expect(ack(1, C.STATUS, status(0, OFF, rx_errors=3)))

    w.case("false-start-swallows-a-frame", "A false header whose LEN covers a real frame: once "
           "its bytes are in and its CRC fails, the real frame inside is found.")
    w.send(bytes((P.START, 8, 0, 0)), show5)
    w.expect(note="waiting for the false frame's 14 bytes")
    w.send(bytes(4))
    w.expect(ack(5, C.SHOW, status(1, OFF, rx_errors=1)), NAK_CRC)

    w.case("byte-by-byte", "A frame arriving one byte at a time.")
    for byte in show5[:-1]:
        w.send(bytes((byte,)))
    w.expect()
    w.send(show5[-1:])
    w.expect(ack(5, C.SHOW, status(1, OFF)))

    w.case("two-frames-in-one-burst", "Frames arriving together are answered in order.")
    w.send(frame(1, C.SET_ALL, sb) + frame(2, C.SHOW))
    w.expect(ack(1, C.SET_ALL), ack(2, C.SHOW, status(1, sb)))

    # --- timeouts (frame gap) ----------------------------------------------------------
    part = frame(1, C.SET_ALL, sa)
    w.case("frame-gap", "A partial frame is dropped once the line is idle for more than the "
           "frame gap: NAK, counted; the line works afterwards.")
    w.send(part[:10])
    w.wait(1)
    w.expect(note="1 ms idle is within the frame gap")
    w.wait(2)
    w.expect(NAK_CRC)
    w.send(part)
    w.expect(ack(1, C.SET_ALL))
    w.send(frame(2, C.STATUS))
    w.expect(ack(2, C.STATUS, status(0, OFF, rx_errors=1)))

    w.case("slow-frame-within-the-gap", "Pauses shorter than the frame gap do not break a frame.")
    w.send(part[:40])
    w.wait(1)
    w.send(part[40:60])
    w.wait(1)
    w.send(part[60:])
    w.expect(ack(1, C.SET_ALL))

    w.case("frame-gap-rescans", "A false START with a long LEN hides a real frame; at the frame "
           "gap the false START is dropped and the real frame inside is answered.")
    w.send(bytes((P.START, 150)), show5)
    w.wait(1)
    w.expect()
    w.wait(3)
    w.expect(ack(5, C.SHOW, status(1, OFF, rx_errors=1)), NAK_CRC)

    corrupt_len = flip(part, 1, 2)  # LEN 73 -> 77: the receiver waits for 4 bytes too many
    w.case("corrupted-length-then-retransmission", "A corrupted LEN swallows the start of the "
           "host's retransmission; the CRC then fails and the retransmission is found.")
    w.send(corrupt_len)
    w.expect()
    w.send(part)
    w.expect(ack(1, C.SET_ALL), NAK_CRC)
    w.send(frame(2, C.SHOW))
    w.expect(ack(2, C.SHOW, status(1, sa, rx_errors=1)))
    w.shown(sa)

    w.case("corrupted-length-then-idle", "A corrupted LEN and no retransmission: the frame gap "
           "ends the wait; the bytes held are rescanned.")
    w.send(corrupt_len)
    w.wait(5)
    w.expect(NAK_CRC)
    w.send(frame(2, C.STATUS))
    w.expect(ack(2, C.STATUS, status(0, OFF, rx_errors=1)))
    return w


def main(argv: list[str]) -> int:
    text = build().text()
    if "--check" in argv:
        if OUT.read_text() != text:
            print(f"{OUT} is stale: run python {Path(__file__).relative_to(Path.cwd())}",
                  file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text)
    print(f"wrote {OUT} ({build().cases} cases)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
