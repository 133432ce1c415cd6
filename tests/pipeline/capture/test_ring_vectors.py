"""The ring protocol's conformance vectors (firmware/vectors/protocol.vec), one file for both
implementations: the Python RingDevice and the C firmware core (byte-exact, on a simulated
clock), and both emulators behind a real pty (frame by frame, in real time)."""

from __future__ import annotations

import subprocess
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import pytest
import serial

from helpers import REPO
from pipeline.capture import protocol as P
from pipeline.capture.emulator import RingDevice

VECTORS = REPO / "firmware" / "vectors" / "protocol.vec"


@dataclass
class Case:
    name: str
    line: int
    device: dict = field(default_factory=dict)
    steps: list = field(default_factory=list)  # (line, directive, bytes | int)


def load_vectors(path=VECTORS) -> list[Case]:
    """Parse the vector file (format in its header)."""
    cases: list[Case] = []
    for n, raw in enumerate(path.read_text().splitlines(), 1):
        text = raw.split("#", 1)[0].strip()
        if not text:
            continue
        word, _, arg = text.partition(" ")
        if word == "case":
            cases.append(Case(arg.strip(), n))
        elif word == "device":
            cases[-1].device = dict(kv.split("=", 1) for kv in arg.split())
        elif word == "wait":
            cases[-1].steps.append((n, word, int(arg)))
        elif word in ("send", "expect", "shown"):
            cases[-1].steps.append((n, word, bytes.fromhex(arg.replace("|", " "))))
        else:
            raise ValueError(f"{path}:{n}: unknown directive {word!r}")
    return cases


CASES = load_vectors()


def device_kwargs(case: Case) -> dict:
    d = case.device
    return {"led_count": int(d.get("leds", 24)), "version": int(d.get("version", 1)),
            "firmware": d.get("firmware", "vectors")}


def shown_bytes(levels: np.ndarray, brightness: float) -> bytes:
    """An LED state as the vector file writes it (levels, then the brightness byte)."""
    return np.asarray(np.rint(levels * 255), np.uint8).tobytes() + bytes((round(brightness * 255),))


def test_vector_file_is_what_its_generator_writes():
    r = subprocess.run([sys.executable, str(VECTORS.parent / "make_vectors.py"), "--check"],
                       capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    names = [c.name for c in CASES]
    assert len(names) == len(set(names)) and len(CASES) >= 35
    # Every command, every NAK code a device sends, resync and timeouts are covered.
    sent = b"".join(s[2] for c in CASES for s in c.steps if s[1] == "send")
    replies = [f for c in CASES for s in c.steps if s[1] == "expect" for f in P.FrameParser().feed(s[2])]
    assert {f.cmd for f in P.FrameParser().feed(sent)} >= {int(c) for c in P.Command if c < 0x80}
    naks = {f.payload[1] for f in replies if f.cmd == P.Command.NAK}
    assert naks == {P.NakCode.BAD_CRC, P.NakCode.UNKNOWN_COMMAND, P.NakCode.BAD_LENGTH,
                    P.NakCode.BAD_ARGUMENT}
    assert any(s[1] == "wait" for c in CASES for s in c.steps)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_python_device_passes_the_vector(case):
    """RingDevice, byte for byte, with a simulated clock (milliseconds in the file)."""
    out: list[bytes] = []
    now = [0.0]
    dev = RingDevice(**device_kwargs(case), send=out.append, clock=lambda: now[0] / 1000.0)
    for line, word, arg in case.steps:
        where = f"{case.name} (protocol.vec line {line})"
        if word == "send":
            dev.receive(arg)
        elif word == "wait":
            now[0] += arg
            dev.poll()
        elif word == "expect":
            got = b"".join(out)
            out.clear()
            assert got.hex(" ") == arg.hex(" "), where
        else:
            assert shown_bytes(*dev.led_state()) == arg, where
    assert not out, f"{case.name}: the device sent bytes no expect line accounts for"


def _frames(data: bytes) -> tuple[list[P.Frame], int]:
    """Replies other than NAK BAD_CRC, and how many NAK BAD_CRC."""
    frames = P.FrameParser().feed(data)
    crc_nak = P.Frame(0, P.Command.NAK, bytes((0, P.NakCode.BAD_CRC)))
    return [f for f in frames if f != crc_nak], sum(f == crc_nak for f in frames)


def test_every_vector_over_the_pty(ring_backend):
    """Each case through a real pty to a fresh emulator of each backend, in real time.

    Real time on a shared machine cannot promise pauses shorter than the 2 ms frame gap, so
    bytes separated only by such pauses (or by an "expect nothing") go out as one write, and
    longer waits sleep at least that long; the sub-gap timing itself is checked byte-exactly
    on the simulated clocks above. The pty may merge or split writes, which moves NAK BAD_CRC
    frames (one per burst the device saw): those are checked for presence, every other reply
    byte for byte, in order."""
    for case in CASES:
        with ring_backend.emulator(**device_kwargs(case)) as emu:
            port = serial.Serial(emu.path, timeout=0)
            try:
                _run_over_pty(case, emu, port)
            finally:
                port.close()


def _run_over_pty(case: Case, emu, port) -> None:
    pending = b""  # bytes to send in one write
    for line, word, arg in case.steps:
        where = f"{case.name} (protocol.vec line {line})"
        if word == "send":
            pending += arg
            continue
        if word == "wait" and arg <= 2 or word == "expect" and not arg:
            continue
        port.write(pending)
        pending = b""
        if word == "wait":
            time.sleep(arg / 1000.0)
        elif word == "expect":
            want, want_naks = _frames(arg)
            got = b""
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                got += port.read(4096)
                frames, naks = _frames(got)
                if len(frames) >= len(want) and (naks or not want_naks):
                    break
                time.sleep(0.001)
            time.sleep(0.005)  # a NAK due after the last reply of the burst
            frames, naks = _frames(got + port.read(4096))
            assert frames == want, where
            assert bool(naks) == bool(want_naks), (where, naks, want_naks)
        else:
            assert shown_bytes(*emu.led_state()) == arg, where
