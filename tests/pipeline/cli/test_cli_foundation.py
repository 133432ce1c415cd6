"""The CLI through a real subprocess: groups, unimplemented commands, cache maintenance."""

import json
import shutil
import subprocess

import pytest

from helpers import run_cli
from pipeline.base.store import StageStore
from schema_examples import example_record

GROUPS = ["sim", "capture", "calibrate", "reconstruct", "run", "batch", "bench", "cache", "import", "eval", "demo"]


def test_help_lists_every_command_group():
    r = run_cli("--help")
    assert r.returncode == 0
    for g in GROUPS:
        assert f"\n    {g}" in r.stdout, g


def test_group_without_subcommand_shows_its_help_and_fails():
    r = run_cli("cache")
    assert r.returncode == 2 and "verify" in r.stderr


@pytest.mark.skipif(shutil.which("iristac") is None, reason="package not installed (CI installs it)")
def test_console_script_is_installed():
    r = subprocess.run(["iristac", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.startswith("iristac ")


def _store_with_entries(root):
    s = StageStore(root)
    good = s.key("depth", 1, {"integrator": "fc"})
    s.put(good, example_record("depth"))
    bad = s.key("depth", 1, {"integrator": "dst"})
    s.put(bad, example_record("depth"))
    s.path_for(bad).write_bytes(b"\x00" * 64)
    temp = root / "depth" / f".{'a' * 32}.999999999.abc.tmp.h5"  # no such pid: a crashed writer
    temp.write_bytes(b"partial")
    return s, good, bad, temp


def test_cache_ls_verify_gc_clear(tmp_path):
    root = tmp_path / "store"
    s, good, bad, temp = _store_with_entries(root)

    r = run_cli("cache", "ls", "--cache", root, "--json")
    assert r.returncode == 0, r.stderr
    kinds = sorted(e["kind"] for e in json.loads(r.stdout)["entries"])
    assert kinds == ["entry", "entry", "temp"]

    r = run_cli("cache", "verify", "--cache", root)
    assert r.returncode == 1
    bad_lines = [l for l in r.stdout.splitlines() if l.startswith("BAD")]
    assert len(bad_lines) == 1 and str(s.path_for(bad)) in bad_lines[0]
    assert "Traceback" not in r.stdout + r.stderr

    r = run_cli("cache", "gc", "--cache", root, "--json")
    assert r.returncode == 0 and json.loads(r.stdout)["removed"] == [str(temp)] and not temp.exists()

    s.path_for(bad).unlink()
    r = run_cli("cache", "verify", "--cache", root, "--json")
    assert r.returncode == 0 and json.loads(r.stdout) == {"root": str(root), "checked": 1, "bad": []}

    r = run_cli("cache", "clear", "--cache", root)
    assert r.returncode == 0 and not s.path_for(good).exists()


def test_cache_uses_environment_variable(tmp_path):
    root = tmp_path / "envstore"
    StageStore(root).put(StageStore(root).key("depth", 1, {}), example_record("depth"))
    r = run_cli("cache", "ls", "--json", env={"IRISTAC_CACHE": str(root)})
    assert len(json.loads(r.stdout)["entries"]) == 1


def test_unimplemented_commands_say_so_and_exit_nonzero(capsys):
    """Every command still registered through ``not_implemented`` fails plainly."""
    import argparse

    from pipeline.cli._common import EXIT_NOT_IMPLEMENTED, not_implemented

    parser = argparse.ArgumentParser(prog="iristac")
    sub = parser.add_subparsers()
    not_implemented(sub, "future", "a future command", "some issue")
    args = parser.parse_args(["future", "x", "y"])
    assert args.func(args) == EXIT_NOT_IMPLEMENTED
    assert "not implemented yet (some issue)" in capsys.readouterr().err
