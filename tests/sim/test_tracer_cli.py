"""``iristac sim trace|section|optimize-lens|synthesize``."""

import json

import numpy as np
import torch

from helpers import run_cli
from pipeline.cli import main
from sim.lens_design import TRACE_KEYS
from sim.synthesize import load_illumination

# Two cores shared by several test runs: a second intra-op thread mostly waits on barriers
# (measured 4-10x slower per op under that load), so the tracer tests run single-threaded.
torch.set_num_threads(1)
ONE_THREAD = {"OMP_NUM_THREADS": "1"}


def test_trace_json_keys_and_bad_scene(capsys):
    r = run_cli("sim", "trace", "plano-sphere", "--rays", "4000", "--sampler", "sobol", "--json", env=ONE_THREAD)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert set(out) == set(TRACE_KEYS)
    assert out["rays"] == 4000 and out["lens"] is True and out["energy_residual"] < 1e-6
    assert 0 < out["fraction_on_screen"] <= 1 and out["rays_per_second"] > 0
    assert main(["sim", "trace", "no-such-scene"]) == 2
    err = capsys.readouterr().err
    assert "no-such-scene" in err and len(err.strip().splitlines()) == 1
    assert main(["sim", "trace", "default", "--device", "no-such-device"]) == 2
    assert "--device 'no-such-device'" in capsys.readouterr().err


def test_synthesize_writes_and_caches(tmp_path, capsys):
    drive = np.zeros((2, 24, 3))
    drive[0] = 1.0
    drive[1, :8, 0] = 1.0
    np.save(tmp_path / "drive.npy", drive)
    args = ["sim", "synthesize", "default", "--shape", "6", "8", "--mm-per-px", "4", "--rays", "4000",
            "--out", str(tmp_path / "ill.h5"), "--cache", str(tmp_path / "cache"), "--drive",
            str(tmp_path / "drive.npy"), "--json"]
    a = run_cli(*args, env=ONE_THREAD)
    assert a.returncode == 0, a.stderr
    ja = json.loads(a.stdout)
    assert ja["cached"] is False and ja["shape"] == [6, 8] and ja["patterns"] == 2
    b = run_cli(*args, env=ONE_THREAD)
    assert json.loads(b.stdout)["cached"] is True and json.loads(b.stdout)["key"] == ja["key"]
    m = load_illumination(tmp_path / "ill.h5")
    assert m.V.shape == (24, 6, 8, 3) and m.meta["light_matrices"].shape == (2, 3, 6, 8, 3)
    np.save(tmp_path / "bad.npy", np.zeros((2, 5, 3)))
    args[args.index(str(tmp_path / "drive.npy"))] = str(tmp_path / "bad.npy")
    assert main(args[1:] if args[0] == "iristac" else args) == 2
    assert "drive must have shape (P, 24, 3)" in capsys.readouterr().err


def test_section_and_optimize_lens_in_process(tmp_path, capsys):
    png = tmp_path / "sec.png"
    assert main(["sim", "section", "default", "--out", str(png), "--rays", "7", "--no-image", "--json"]) == 0
    assert png.stat().st_size > 1000 and json.loads(capsys.readouterr().out)["rays"] == 7
    out = tmp_path / "opt"
    code = main(["sim", "optimize-lens", "default-v1", "--vary", "apex_z", "bottom_z", "--evaluations", "6",
                 "--rays", "2000", "--grid", "6", "--confirm-rays", "4000", "--tolerance-rays", "2000",
                 "--threads", "1", "--no-progress", "--out", str(out), "--json"])
    assert code == 0
    res = json.loads(capsys.readouterr().out)
    from sim.lens_design import OPTIMIZE_KEYS

    assert set(res) == set(OPTIMIZE_KEYS) and res["evaluations"] == 6 and res["varied"] == ["apex_z", "bottom_z"]
    assert {"fraction_on_screen", "uniformity_cv", "valid_fraction", "design", "evaluations", "seconds"} <= set(res)
    assert (out / "default-v1-optimized.yaml").exists() and (out / "trajectory.png").exists()
    # Bad input: one clear line naming the option, nothing written.
    assert main(["sim", "optimize-lens", "default-v1", "--max-cv", "lots", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "--max-cv" in err and "'bare'" in err and not (tmp_path / "x").exists()
    assert main(["sim", "optimize-lens", "default-v1", "--bound", "wings", "1", "2"]) == 2
    assert "--bound: unknown parameter 'wings'" in capsys.readouterr().err
