"""Ring protocol: encode/decode round trips, CRC properties, a parser that survives garbage."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.capture import protocol as P

frames_st = st.builds(
    P.Frame,
    seq=st.integers(0, 255),
    cmd=st.sampled_from(list(P.Command)),
    payload=st.binary(max_size=P.MAX_PAYLOAD),
)


def test_crc_check_value_and_layout():
    assert P.crc16(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE reference value
    raw = P.encode_frame(P.Frame(seq=9, cmd=P.Command.SET_ONE, payload=b"\x02\x10\x20\x30"))
    assert raw[0] == P.START and raw[1] == 4 and raw[2] == 9 and raw[3] == P.Command.SET_ONE
    assert int.from_bytes(raw[-2:], "little") == P.crc16(raw[1:-2])
    # A full SET_ALL for 24 LEDs is the "about 80 bytes" of the spec.
    assert len(P.encode_frame(P.Frame(1, P.Command.SET_ALL, bytes(73)))) == 79


@given(frames_st)
def test_frame_round_trip(frame):
    assert P.FrameParser().feed(P.encode_frame(frame)) == [frame]


@given(frames_st, st.data())
def test_every_single_bit_flip_is_rejected(frame, data):
    raw = bytearray(P.encode_frame(frame))
    bit = data.draw(st.integers(0, 8 * len(raw) - 1))
    raw[bit // 8] ^= 1 << (bit % 8)
    parser = P.FrameParser()
    got = parser.feed(bytes(raw)) + parser.resync()
    assert frame not in got
    assert got == []


def test_encode_rejects_out_of_range_fields():
    with pytest.raises(ValueError, match="seq"):
        P.encode_frame(P.Frame(seq=256, cmd=P.Command.OFF))
    with pytest.raises(ValueError, match="payload"):
        P.encode_frame(P.Frame(seq=1, cmd=P.Command.SET_ALL, payload=bytes(P.MAX_PAYLOAD + 1)))


def test_state_payload_hello_status_round_trips():
    rng = np.random.default_rng(1)
    drive = rng.random((24, 3))
    levels, b = P.quantize_state(drive, 0.6)
    assert np.abs(levels / 255.0 - drive).max() <= 0.5 / 255 + 1e-12
    back, b2 = P.parse_state_payload(P.state_payload(levels, b), 24)
    assert np.array_equal(back, levels) and b2 == b == 153
    hello = P.Hello(version=1, led_count=24, firmware="fw-1.2")
    assert P.decode_hello(P.encode_hello(hello)) == hello
    status = P.Status(latch_count=70000, shown_crc=0xBEEF, rx_crc_errors=3, duplicates=4)
    assert P.decode_status(P.encode_status(status)) == status
    with pytest.raises(ValueError, match="73 bytes"):
        P.parse_state_payload(bytes(72), 24)
    with pytest.raises(ValueError, match=r"\(L, 3\)"):
        P.quantize_state(np.zeros((24, 4)), 1.0)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        P.quantize_state(np.full((24, 3), 1.5), 1.0)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.tuples(st.binary(max_size=40), frames_st), min_size=1, max_size=6),
    st.binary(max_size=40),
    st.lists(st.integers(1, 50), min_size=1, max_size=20),
)
def test_parser_fed_garbage_never_crashes_and_resyncs(pieces, tail, chunk_sizes):
    """Garbage (possibly full of START bytes and bogus lengths) around real frames: the parser
    never raises, and after the line goes idle every real frame has come out, in order."""
    stream = b"".join(g + P.encode_frame(f) for g, f in pieces) + tail
    parser = P.FrameParser()
    got: list[P.Frame] = []
    i = 0
    k = 0
    while i < len(stream):  # deliver in arbitrary chunks, as a serial port does
        n = chunk_sizes[k % len(chunk_sizes)]
        got += parser.feed(stream[i : i + n])
        i += n
        k += 1
    got += parser.resync()
    assert parser.pending == 0
    want = [f for _, f in pieces]
    it = iter(got)
    assert all(any(g == w for g in it) for w in want), (want, got)  # want is a subsequence


@settings(max_examples=60, deadline=None)
@given(st.binary(min_size=0, max_size=600))
def test_parser_pure_garbage(garbage):
    parser = P.FrameParser()
    parser.feed(garbage)
    parser.resync()
    assert parser.pending == 0
    # And the line still works afterwards.
    frame = P.Frame(3, P.Command.STATUS)
    assert parser.feed(P.encode_frame(frame)) == [frame]


def test_false_start_swallowing_a_frame_is_recovered_without_idle():
    """A bogus header whose length covers a real frame: the real frame is found once the
    bogus frame's bytes are all in and its CRC fails (no idle needed)."""
    good = P.encode_frame(P.Frame(5, P.Command.SHOW))
    bogus = bytes((P.START, 8, 0, 0))  # wants 8 + 2 more bytes after its header
    parser = P.FrameParser()
    assert parser.feed(bogus + good) == []
    assert parser.feed(bytes(10)) == [P.Frame(5, P.Command.SHOW)]
    assert parser.crc_errors == 1
