"""DiLiGenT layout: a small folder written by the test, imported at full bit depth, solved and evaluated."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import scipy.io

from helpers import run_cli
from pipeline.base.errors import UserError
from pipeline.base.store import read_record
from pipeline.capture.diligent import import_diligent, read_diligent
from pipeline.results.evaluate import evaluate_normals
from pipeline.workflows.reconstruct import reconstruct
from support_recon import _one_torch_thread, sphere_cap  # noqa: F401

H, W = 24, 28


def write_diligent_folder(d, seed=0):
    """A ball under 8 lights near the view direction, coloured albedo, 16-bit PNGs (BGR on disk)."""
    rng = np.random.default_rng(seed)
    _, n = sphere_cap((H, W), 0.1, 1.2, 1.2)  # a hemisphere: normals cover the ball
    mask = n[..., 2] > 0.75  # visible and never in attached shadow for these lights
    n = np.where(mask[..., None], n, 0.0)
    az = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    el = np.radians(65 + 10 * rng.random(8))
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    ints = rng.uniform(0.6, 1.0, (8, 3))
    albedo = np.array([0.9, 0.6, 0.3])
    names = []
    for p in range(8):
        shading = np.clip(n @ dirs[p], 0, None)[..., None]
        img = np.round(50000 * albedo * ints[p] * shading).astype(np.uint16)
        name = f"{p + 1:03d}.png"
        cv2.imwrite(str(d / name), img[..., ::-1])
        names.append(name)
    (d / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(d / "light_directions.txt", dirs)
    np.savetxt(d / "light_intensities.txt", ints)
    cv2.imwrite(str(d / "mask.png"), mask.astype(np.uint8) * 255)
    scipy.io.savemat(d / "Normal_gt.mat", {"Normal_gt": n})
    return n, mask


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("ball")
    n, mask = write_diligent_folder(d)
    return d, n, mask


def test_read_at_full_depth_in_rgb(folder):
    d, n, mask = folder
    obj = read_diligent(d)
    assert obj.images.dtype == np.uint16 and obj.images.max() > 255  # not reduced to 8 bits
    # Red albedo (0.9) is the largest: the channel order is RGB.
    inside = obj.images[0][mask]
    assert (inside[:, 0] >= inside[:, 2]).all() and inside[:, 0].mean() > 2 * inside[:, 2].mean()
    assert obj.mask.tolist() == mask.tolist()
    np.testing.assert_allclose(obj.normals_gt, n)


def test_import_reconstruct_and_eval(folder, tmp_path):
    d, n, mask = folder
    summary = import_diligent(d, tmp_path / "capture.h5")
    assert summary["images"] == 8 and summary["has_ground_truth"]
    cap = read_record(tmp_path / "capture.h5", schema="capture")
    assert cap.data["frames"].shape == (1, 8, H, W, 3) and cap.meta["source"] == "diligent"
    res = reconstruct(tmp_path / "capture.h5", solver="lstsq", integrator="sparse", out=tmp_path / "out",
                      store=tmp_path / "cache", images=False, save="confidence,albedo")
    # 16-bit data without shadows inside the mask: least squares is essentially exact.
    assert res.summary["normal_mean_error_deg"] < 0.05
    r = evaluate_normals(tmp_path / "out" / "normals.h5", d / "Normal_gt.mat", d / "mask.png")
    assert r["pixels"] == int(mask.sum()) and r["mean_deg"] < 0.05 and r["median_deg"] <= r["mean_deg"] + 0.05
    # Per-channel albedo is recovered up to the common scale.
    alb = res.normals.data["albedo"][0][mask]
    np.testing.assert_allclose(alb[:, 1] / alb[:, 0], 0.6 / 0.9, rtol=1e-3)
    with pytest.raises(UserError, match="reference"):
        reconstruct(tmp_path / "capture.h5", ratio=True, store=tmp_path / "cache")


def test_cli_import_and_eval_json(folder, tmp_path):
    d, n, mask = folder
    r = run_cli("import", "diligent", d, "--out", tmp_path / "cap.h5", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["images"] == 8
    np.save(tmp_path / "pred.npy", n + np.array([0.05, 0, 0]) * mask[..., None])
    r = run_cli("eval", "normals", tmp_path / "pred.npy", "--gt", d / "Normal_gt.mat", "--mask", d / "mask.png",
                "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert set(out) == {"mean_deg", "median_deg", "pixels"} and out["pixels"] == int(mask.sum())
    assert 1.0 < out["mean_deg"] < 4.0


def test_bad_folders_name_the_file(tmp_path):
    with pytest.raises(UserError, match="filenames.txt"):
        read_diligent(tmp_path)
    (tmp_path / "filenames.txt").write_text("a.png\nb.png\n")
    np.savetxt(tmp_path / "light_directions.txt", np.eye(3))
    np.savetxt(tmp_path / "light_intensities.txt", np.ones((3, 3)))
    with pytest.raises(UserError, match=r"light_directions.txt: 3 lines, but filenames.txt lists 2"):
        read_diligent(tmp_path)
    r = run_cli("eval", "normals", tmp_path / "nope.npy", "--gt", tmp_path / "nope.mat")
    assert r.returncode == 2 and "nope.npy: file not found" in r.stderr
