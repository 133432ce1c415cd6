"""``iristac sim modes|render|uniformity`` through a subprocess."""

import json

import numpy as np

from helpers import run_cli
from pipeline.base.store import read_record


def test_sim_modes_json_and_bad_file(tmp_path):
    r = run_cli("sim", "modes", "--json")
    assert r.returncode == 0, r.stderr
    modes = {m["name"]: m for m in json.loads(r.stdout)["modes"]}
    assert {"point", "monochromatic", "trichromatic", "multicolour"} <= set(modes)
    assert modes["point"]["frames"] == 24 and set(modes["point"]) == {"name", "frames", "leds", "patterns",
                                                                      "description", "file"}
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nleds: 24\nframes: [{name: a, drive: [[2, 0, 0]]}]\n")
    r = run_cli("sim", "modes", str(bad))
    assert r.returncode == 2 and "bad.yaml" in r.stderr and "frames/0/drive" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_sim_render_sphere_and_height_file(tmp_path):
    r = run_cli("sim", "render", "--sphere", "2", "0.6", "--shape", "30", "40", "--mm-per-px", "0.2",
                "--mode", "trichromatic", "--out", tmp_path / "a", "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert set(res) == {"capture", "pngs", "mode", "patterns", "shape", "mm_per_px", "exposure", "effects"}
    rec = read_record(res["capture"], schema="capture")
    assert rec.data["frames"].shape == (1, 1, 30, 40, 3) and rec.meta["source"] == "virtual"
    assert rec.data["truth/height"].max() > 0.55
    import cv2

    png = cv2.imread(res["pngs"][0], cv2.IMREAD_UNCHANGED)[..., ::-1]
    np.testing.assert_array_equal(png, rec.data["frames"][0, 0])  # RGB on disk as in the file
    h = np.zeros((20, 30))
    h[5:15, 10:20] = 0.2
    np.save(tmp_path / "h.npy", h)
    settings = tmp_path / "fx.yaml"
    settings.write_text("exposure: 300000\nbit_depth: 16\nvignetting: 0.3\n")
    r = run_cli("sim", "render", "--height", tmp_path / "h.npy", "--mm-per-px", "0.3", "--settings", settings,
                "--out", tmp_path / "b", "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["shape"] == [20, 30] and res["effects"] == ["attached_shadows", "vignetting", "quantization"]
    assert read_record(res["capture"]).data["frames"].dtype == np.uint16
    settings.write_text("exposure: 1\nvignette: 0.3\n")
    r = run_cli("sim", "render", "--out", tmp_path / "c", "--settings", settings, "--shape", "8", "8")
    assert r.returncode == 2 and "fx.yaml" in r.stderr and "vignette" in r.stderr


def test_sim_uniformity_json_and_figure(tmp_path):
    r = run_cli("sim", "uniformity", "trichromatic", "multicolour", "--shape", "24", "32", "--mm-per-px", "0.5",
                "--figure", tmp_path / "u.png", "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert set(res) == {"modes", "frames", "figure"} and (tmp_path / "u.png").is_file()
    assert res["modes"]["multicolour"]["G"]["cv_mean"] < res["modes"]["trichromatic"]["G"]["cv_mean"]


def test_sim_render_and_uniformity_take_a_traced_illumination_file(tmp_path):
    import json

    from pipeline.base.store import read_record
    from sim.synthesize import save_illumination, synthesize

    ill = save_illumination(synthesize("default", (24, 32), 0.7, rays=60_000, sampler="sobol"), tmp_path / "ill.h5")
    r = run_cli("sim", "render", "--illumination", ill, "--sphere", "2", "0.5", "--mode", "trichromatic",
                "--out", tmp_path / "r", "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["shape"] == [24, 32] and read_record(res["capture"]).data["frames"].shape == (1, 1, 24, 32, 3)
    r = run_cli("sim", "uniformity", "point", "--illumination", ill, "--json")
    assert r.returncode == 0, r.stderr
    assert "point" in json.loads(r.stdout)["modes"]
