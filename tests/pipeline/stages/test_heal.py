"""A self-healing cache: a bit-flipped or schema-violating entry met by run, reconstruct or
batch is quarantined (kept, never deleted), recomputed, and reported in one warning line;
``--no-heal`` stops on it as before (real CLI, real HDF5 files)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from helpers import run_cli
from pipeline.base.store import StageStore, read_record

CONFIG = {
    "cache": "cache",
    "synthesize": {"model": "bare_ring", "height": 20, "width": 24, "mm_per_px": 0.4},
    "capture": {"render": True, "contacts": 1, "size_mm": 2.0, "depth_mm": 0.4},
    "normals": {"solver": "nearfield"},
    "depth": {"integrator": "dst"},
}


def flip_a_bit(path: Path, dataset: str = "normals") -> None:
    """Flip one bit in the middle of the first stored chunk of ``dataset`` (its checksum then fails)."""
    with h5py.File(path, "r") as f:
        ds = f[dataset]
        info = ds.id.get_chunk_info(0) if ds.chunks else None
        offset = info.byte_offset + info.size // 2 if info else ds.id.get_offset() + ds.id.get_storage_size() // 2
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x10
    path.write_bytes(bytes(data))


def drop_dataset(path: Path, dataset: str = "mask") -> None:
    """A readable HDF5 file that no longer matches its schema."""
    with h5py.File(path, "a") as f:
        del f[dataset]


@pytest.fixture(scope="module")
def seeded(tmp_path_factory):
    d = tmp_path_factory.mktemp("heal")
    (d / "run.yaml").write_text(yaml.safe_dump(CONFIG), encoding="utf-8")
    r = run_cli("run", d / "run.yaml", "--json")
    assert r.returncode == 0, r.stderr
    return d, {s["name"]: s for s in json.loads(r.stdout)["stages"]}


@pytest.fixture
def project(seeded, tmp_path):
    d, stages = seeded
    shutil.copytree(d / "cache", tmp_path / "cache")
    shutil.copy(d / "run.yaml", tmp_path / "run.yaml")
    return tmp_path, stages


def entry(root: Path, stage: str, key: str) -> Path:
    return root / "cache" / stage / f"{key}.h5"


def warnings_of(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("iristac: warning:")]


@pytest.mark.parametrize("damage", [flip_a_bit, drop_dataset])
def test_run_heals_a_bad_entry_and_no_heal_stops_on_it(project, damage):
    root, stages = project
    bad = entry(root, "normals", stages["normals"]["key"])
    damage(bad)
    before = bad.read_bytes()
    r = run_cli("run", root / "run.yaml", "--no-heal", "--json")
    assert r.returncode == 2 and "stage 'normals' failed" in r.stderr and str(bad) in r.stderr
    assert bad.read_bytes() == before  # --no-heal touches nothing
    r = run_cli("run", root / "run.yaml", "--json")
    assert r.returncode == 0, r.stderr
    cached = {s["name"]: s["cached"] for s in json.loads(r.stdout)["stages"]}
    assert cached == {"synthesize": True, "capture": True, "normals": False, "depth": True}
    lines = warnings_of(r.stderr)
    assert len(lines) == 1 and str(bad) in lines[0] and "quarantined" in lines[0], r.stderr
    quarantined = list(bad.parent.glob(f"{bad.stem}.bad-*.h5"))
    assert len(quarantined) == 1 and quarantined[0].read_bytes() == before  # kept as it was
    assert read_record(bad, schema="normals").data["normals"].shape == (1, 20, 24, 3)
    assert StageStore(root / "cache").verify() == []


def test_reconstruct_and_batch_heal_too(project, tmp_path):
    root, stages = project
    cap = entry(root, "capture", stages["capture"]["key"])
    ill = entry(root, "synthesize", stages["synthesize"]["key"])
    bad = entry(root, "depth", stages["depth"]["key"])
    args = [cap, "--illumination", ill, "--solver", "nearfield", "--cache", root / "cache"]
    flip_a_bit(bad, "height")
    r = run_cli("reconstruct", *args, "--out", tmp_path / "out", "--no-images", "--no-heal", "--json")
    assert r.returncode == 2 and str(bad) in r.stderr
    r = run_cli("reconstruct", *args, "--out", tmp_path / "out", "--no-images", "--json")
    assert r.returncode == 0, r.stderr
    assert len(warnings_of(r.stderr)) == 1 and str(bad) in r.stderr
    assert json.loads(r.stdout)["cached"] is False  # the depth was recomputed
    healed = read_record(bad, schema="depth").data["height"]
    flip_a_bit(bad, "height")
    r = run_cli("batch", *args, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["items"][0]["ok"] and len(warnings_of(r.stderr)) == 1
    assert np.array_equal(read_record(bad, schema="depth").data["height"], healed)
    assert len(list(bad.parent.glob("*.bad-*.h5"))) == 2
