"""Host client against the emulator over a real pseudo-terminal (the real pyserial Serial)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.base.errors import UserError
from pipeline.capture import protocol as P
from pipeline.capture.client import (
    RingClient,
    RingDisconnected,
    RingPortError,
    RingProtocolError,
    RingTimeout,
)
from pipeline.capture.emulator import FaultSpec, parse_faults


def test_handshake_and_every_command(ring_backend):
    with ring_backend.emulator(led_count=6, firmware="fw-test") as emu, RingClient(emu.path) as ring:
        assert ring.info == P.Hello(P.PROTOCOL_VERSION, 6, "fw-test")
        drive = np.linspace(0, 1, 18).reshape(6, 3)
        ring.set_all(drive, 0.5)
        d, b = emu.led_state()
        assert d.max() == 0 and b == 0  # loaded, not shown before SHOW
        ring.set_one(2, (1.0, 0.0, 0.25))
        status = ring.show()
        d, b = emu.led_state()
        want = np.floor(drive * 255 + 0.5) / 255
        want[2] = [1.0, 0.0, 64 / 255]
        assert np.allclose(d, want, atol=1e-6) and b == 128 / 255
        assert status.latch_count == 1 and ring.status() == status
        ring.off()
        d, b = emu.led_state()
        assert d.max() == 0 and b == 0
        assert len(emu.history()) == 3  # power-on (off), SHOW, OFF
        assert ring.stats.retries == 0


def test_refused_command_is_a_clear_error(ring_backend):
    with ring_backend.emulator(led_count=4) as emu, RingClient(emu.path) as ring:
        with pytest.raises(RingProtocolError, match="refused SET_ONE.*BAD_ARGUMENT"):
            ring.set_one(9, (1, 1, 1))
        with pytest.raises(RingProtocolError, match="pattern has 5 LEDs but the ring .* has 4"):
            ring.set_all(np.zeros((5, 3)), 1.0)


def test_wrong_port_lists_available_ports():
    with pytest.raises(RingPortError) as err:
        RingClient("/dev/ttyIRISTAC-NOPE").open()
    msg = str(err.value)
    assert "'/dev/ttyIRISTAC-NOPE' does not exist" in msg and "serial ports on this machine" in msg
    assert isinstance(err.value, UserError)


def test_wrong_protocol_version(ring_backend):
    with ring_backend.emulator(version=P.PROTOCOL_VERSION + 1, firmware="future-fw") as emu:
        with pytest.raises(RingProtocolError) as err:
            RingClient(emu.path).open()
    msg = str(err.value)
    assert f"speaks ring protocol version {P.PROTOCOL_VERSION + 1}" in msg
    assert f"this host speaks version {P.PROTOCOL_VERSION}" in msg and "future-fw" in msg


def test_silent_port_times_out_with_a_hint(ring_backend):
    # Every frame lost: nothing ever answers, as on a port with some other device.
    with ring_backend.emulator(faults=FaultSpec(drop=1.0)) as emu:
        with pytest.raises(RingTimeout, match="no IrisTac ring answered HELLO.*is this the ring"):
            RingClient(emu.path, timeout=0.005, max_timeout=0.01, retries=2).open()


def test_disconnect_is_a_clear_error(ring_backend):
    with ring_backend.emulator(faults=parse_faults("disconnect-after=3")) as emu:
        ring = RingClient(emu.path, timeout=0.05)
        ring.open()  # command 1
        ring.set_all(np.zeros((24, 3)), 1.0)  # 2
        ring.show()  # 3, then the device is unplugged
        with pytest.raises(RingDisconnected, match="disconnected during SET_ALL"):
            ring.set_all(np.ones((24, 3)), 1.0)
        ring.close()


def test_delays_give_duplicate_replies_that_are_ignored_and_never_re_executed(ring_backend):
    """A stalled device answers late; the host has already retransmitted, so each command is
    answered twice. The duplicates are ignored and a retransmitted SHOW does not latch twice."""
    faults = FaultSpec(delay=0.3, delay_s=0.02)
    rng = np.random.default_rng(0)
    with ring_backend.emulator(faults=faults, seed=2) as emu, \
            RingClient(emu.path, timeout=0.005, retries=20) as ring:
        n = 40
        for _ in range(n):
            ring.show_pattern(rng.random((24, 3)), 1.0)
        ring.status()
        assert emu.stats.delayed > 0 and emu.stats.duplicates > 0
        assert ring.stats.retries > 0
        assert len(emu.history()) == n + 1  # exactly one latch per pattern, plus power-on
        assert ring.stats.stale_replies > 0


def test_state_history_intervals(ring_backend):
    with ring_backend.emulator(led_count=2) as emu, RingClient(emu.path) as ring:
        ring.show_pattern(np.ones((2, 3)), 1.0)
        ring.off()
        h = emu.history()
        assert [s.brightness for s in h] == [0, 255, 0]
        mid = 0.5 * (h[1].t + h[2].t)
        assert emu.states_during(mid, mid) == [h[1]]
        assert emu.states_during(h[0].t, h[2].t + 1) == h
        assert emu.states_during(h[2].t + 1, h[2].t + 2) == [h[2]]


@pytest.mark.parametrize(
    "spec, match",
    [
        ("drop=2", "drop=2.0 must be a probability"),
        ("lose=0.1", "expected key=value with key one of"),
        ("disconnect-after=x", "disconnect-after='x' is not an integer"),
        ("corrupt", "cannot parse 'corrupt'"),
    ],
)
def test_fault_spec_errors(spec, match):
    with pytest.raises(UserError, match=match):
        parse_faults(spec)


@settings(max_examples=8, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    drop=st.floats(0, 0.2),
    corrupt=st.floats(0, 0.2),
    delay=st.floats(0, 0.1),
)
def test_any_fault_mix_shows_each_pattern_exactly_once(seed, drop, corrupt, delay, ring_backend):
    """Whatever the faults, every confirmed SHOW is one latch of exactly the state sent, in
    order: retries never execute a command twice and never latch a wrong state."""
    rng = np.random.default_rng(seed)
    drives = rng.random((15, 24, 3))
    faults = FaultSpec(drop=drop, corrupt=corrupt, delay=delay, delay_s=0.01)
    with ring_backend.emulator(faults=faults, seed=seed) as emu, RingClient(
        emu.path, timeout=0.004, retries=40, max_timeout=0.05
    ) as ring:
        for d in drives:
            ring.show_pattern(d, 0.5)
        history = emu.history()[1:]
    assert len(history) == len(drives)
    for state, d in zip(history, drives):
        levels, b = P.quantize_state(d, 0.5)
        assert state.same_as(levels, b)
