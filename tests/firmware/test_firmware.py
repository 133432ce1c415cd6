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


def test_host_program_takes_tiny_probabilities(ring_firmware_binary):
    """A subnormal probability is a valid number (strtod flags it ERANGE; found by hypothesis)."""
    r = subprocess.run([str(ring_firmware_binary), "--faults", "delay=2.225073858507e-311",
                        "--duration", "0"], capture_output=True, text=True, timeout=10)
    assert r.returncode == 0, r.stderr


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


def test_cli_capture_through_the_c_firmware(ring_firmware_binary, tmp_path):
    """``iristac capture --emulate --ring-firmware BIN``: the whole CLI path through the C
    firmware with faults; the HELLO names it, no frame is mislabeled, and each reference
    frame lights the side of its LED."""
    import json

    import numpy as np

    from helpers import run_cli
    from pipeline.base.store import read_record

    out = tmp_path / "c.h5"
    r = run_cli("capture", "--emulate", "--ring-firmware", ring_firmware_binary, "--virtual-camera",
                "--mode", "point", "--camera-fps", "500", "--camera-size", "6", "8", "--timeout",
                "0.01", "--faults", "drop=0.05,corrupt=0.05", "--out", out, "--json", timeout=120)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["frames"] == 49 and summary["mislabeled"] == 0
    rec = read_record(out, schema="capture")
    assert rec.meta["device"]["ring"]["firmware"] == "iristac-ring-c/1"
    ref = rec.data["reference"].astype(float).mean(axis=3)
    assert ref[0][:, -1].mean() > ref[0][:, 0].mean() and ref[12][:, 0].mean() > ref[12][:, -1].mean()
    r = run_cli("capture", "--port", "/dev/null", "--ring-firmware", ring_firmware_binary,
                "--camera", "0", "--mode", "point", "--out", tmp_path / "x.h5")
    assert r.returncode == 2 and "--ring-firmware serves the emulated ring; it needs --emulate" in r.stderr
    assert not np.any([p.name == "x.h5" for p in tmp_path.iterdir()])
