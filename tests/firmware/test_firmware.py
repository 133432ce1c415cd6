"""The C ring firmware (firmware/): its own conformance run, portability checks, the host
program's command line, and the freestanding Cortex-M0+ build where a cross compiler exists."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from helpers import REPO

FIRMWARE = REPO / "firmware"
VECTORS = FIRMWARE / "vectors" / "protocol.vec"


def _make(target: str, build) -> subprocess.CompletedProcess:
    return subprocess.run(["make", "-s", "-C", str(FIRMWARE), target, f"BUILD={build}"],
                          capture_output=True, text=True)


def test_c_core_passes_every_vector(ring_firmware_binary):
    """``make -C firmware test``: the C vector runner (every case at clock 0 and across the
    millis() wrap) and the check that the core includes and calls nothing but <stdint.h>,
    <string.h> and the four ring_hal_* functions."""
    cases = sum(line.startswith("case ") for line in VECTORS.read_text().splitlines())
    r = _make("test", ring_firmware_binary.parents[1])
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"{2 * cases} passed, 0 failed" in r.stdout, r.stdout
    assert "includes <stdint.h> and <string.h> only" in r.stdout


def test_c_runner_catches_a_wrong_reply(ring_firmware_binary, tmp_path):
    """The runner fails on one flipped byte of an expected reply (it can fail)."""
    text = VECTORS.read_text().splitlines()
    i = next(i for i, line in enumerate(text) if line.startswith("expect A5"))
    last = text[i][-2:]
    text[i] = text[i][:-2] + ("00" if last != "00" else "01")
    bad = tmp_path / "bad.vec"
    bad.write_text("\n".join(text) + "\n")
    runner = ring_firmware_binary.parent / "vector_runner"
    _make("test", ring_firmware_binary.parents[1])  # builds the runner
    r = subprocess.run([str(runner), str(bad)], capture_output=True, text=True)
    assert r.returncode == 1 and "2 failed" in r.stdout and "FAIL" in r.stdout, r.stdout


@pytest.mark.parametrize("args, message", [
    (["--faults", "drop=2"], "--faults: drop=2 must be a probability in [0, 1]"),
    (["--faults", "lose=0.1"], "--faults: unknown key 'lose'"),
    (["--faults", "corrupt"], "--faults: cannot parse 'corrupt'"),
    (["--leds", "30"], "--leds must be in 1..24"),
    (["--seed"], "missing value after --seed"),
])
def test_host_program_bad_arguments(ring_firmware_binary, args, message):
    r = subprocess.run([str(ring_firmware_binary), *args], capture_output=True, text=True, timeout=10)
    assert r.returncode == 2 and message in r.stderr, r.stderr


def test_host_program_prints_its_pty_and_stops_on_its_own(ring_firmware_binary):
    r = subprocess.run([str(ring_firmware_binary), "--duration", "0.2"], capture_output=True,
                       text=True, timeout=10)
    assert r.returncode == 0 and r.stdout.startswith("/dev/"), (r.stdout, r.stderr)


@pytest.mark.skipif(shutil.which("arm-none-eabi-gcc") is None,
                    reason="no arm-none-eabi-gcc (apt-get install gcc-arm-none-eabi "
                    "libnewlib-arm-none-eabi) for the Cortex-M0+ build")
def test_cortex_m0plus_freestanding_build(tmp_path):
    r = _make("cortex-m0plus", tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "ring-m0plus.elf" in r.stdout and "ring_device_t" in r.stdout
