"""``reconstruct`` / ``batch`` on a masked photometric-stereo capture: only the mask is solved,
``--mask`` replaces it, bad masks and too few lights are one clear error, version-1 captures
(zero references) are still read."""

from __future__ import annotations

import json

import cv2
import h5py
import numpy as np
import pytest

from helpers import run_cli
from pipeline.base.errors import UserError
from pipeline.base.store import Record, StoreError, read_record, write_record
from pipeline.workflows.reconstruct import reconstruct
from sim.ps_objects import dome_lights, render_ps_capture, sphere_object
from support_recon import _one_torch_thread  # noqa: F401

FRAME = (40, 52)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    d = tmp_path_factory.mktemp("ps")
    dirs, ints = dome_lights(4, 6)
    rec = render_ps_capture(sphere_object((32, 32), 14), dirs, ints, specular=0.04, roughness=0.3,
                            frame_shape=FRAME, seed=5)
    return write_record(d / "ps.h5", rec), rec


def test_only_the_mask_is_solved_and_robust_beats_least_squares(capture, tmp_path):
    path, rec = capture
    m = rec.data["mask"]
    res = {}
    for solver in ("lstsq", "robust", "cauchy"):
        r = reconstruct(path, solver=solver, integrator="dst", store=tmp_path / "c", images=False, save="all")
        n, d = r.normals.data, r.depth.data
        assert not n["mask"][0][~m].any() and (n["count"][0][~m] == 0).all()
        assert (n["normals"][0][~m] == [0, 0, 1]).all() and np.isfinite(n["residual"]).all()
        assert not d["mask"][0][~m].any() and (d["height"][0][~m] == 0).all()
        assert n["mask"][0][m].mean() > 0.98 and r.normals.meta["region_pixels"] == int(m.sum())
        res[solver] = r.summary["normal_mean_error_deg"]
    assert res["robust"] < 1.0 and res["robust"] < 0.5 * res["lstsq"], res
    sparse = reconstruct(path, solver="robust", integrator="sparse", store=tmp_path / "c", images=False)
    assert sparse.summary["normal_mean_error_deg"] == res["robust"]  # the normals stage is shared (cached)
    assert not sparse.depth.data["mask"][0][~m].any()


def test_user_mask_replaces_the_captures(capture, tmp_path):
    path, rec = capture
    user = np.zeros(FRAME, np.uint8)
    user[10:25, 15:30] = 255
    cv2.imwrite(str(tmp_path / "roi.png"), user)
    a = reconstruct(path, solver="lstsq", store=tmp_path / "c", images=False)
    b = reconstruct(path, solver="lstsq", store=tmp_path / "c", images=False, mask=tmp_path / "roi.png")
    assert not b.summary["cached"]  # a different region is a different result
    roi = user > 0
    assert not b.normals.data["mask"][0][~roi].any()
    both = roi & rec.data["mask"]
    np.testing.assert_allclose(b.normals.data["normals"][0][both], a.normals.data["normals"][0][both], atol=1e-6)
    r = run_cli("reconstruct", path, "--solver", "robust", "--mask", tmp_path / "roi.png", "--out", tmp_path / "o",
                "--cache", tmp_path / "c", "--no-images", "--json")
    assert r.returncode == 0, r.stderr
    assert 0 < json.loads(r.stdout)["valid_fraction"] <= roi.mean()


def test_bad_masks_are_one_line_errors_naming_the_file(capture, tmp_path):
    path, rec = capture
    cv2.imwrite(str(tmp_path / "small.png"), np.full((10, 10), 255, np.uint8))
    cv2.imwrite(str(tmp_path / "empty.png"), np.zeros(FRAME, np.uint8))
    for name, msg in [("small.png", r"small.png: mask has shape \(10, 10\), expected \(H, W\) = \(40, 52\)"),
                      ("empty.png", "empty.png: mask selects no pixels"),
                      ("missing.png", "missing.png: mask file not found")]:
        r = run_cli("reconstruct", path, "--mask", tmp_path / name, "--out", tmp_path / "o", "--cache", tmp_path / "c")
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and __import__("re").search(msg, lines[0]), lines
        assert not (tmp_path / "o").exists()
    # The capture's own mask: empty, or (in memory: a file could not be written) of the wrong size.
    bad = Record("capture", dict(rec.data, mask=np.zeros(FRAME, bool)), dict(rec.meta))
    with pytest.raises(UserError, match="dataset 'mask' selects no pixels"):
        reconstruct(bad, store=tmp_path / "c", images=False)
    bad.data["mask"] = np.ones((3, 3), bool)
    with pytest.raises(StoreError, match=r"dataset 'mask' has H=3"):
        write_record(tmp_path / "bad.h5", bad)
    with pytest.raises(UserError, match=r"dataset 'mask' has shape \(3, 3\), expected \(H, W\) = \(40, 52\)"):
        reconstruct(bad, store=tmp_path / "c", images=False)


def test_fewer_than_three_lights_is_one_clear_error(capture, tmp_path):
    path, rec = capture
    data = dict(rec.data)
    lv = data["lights/light_vectors"].copy()
    lv[:] = lv[0]  # every light from one direction (rank 1), or two
    lv[1::2] = rec.data["lights/light_vectors"][1]
    data["lights/light_vectors"] = lv
    two = write_record(tmp_path / "two.h5", Record("capture", data, dict(rec.meta)))
    r = run_cli("reconstruct", two, "--out", tmp_path / "o", "--cache", tmp_path / "c")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "two.h5:lights/light_vectors: the 72 light vectors span 2 independent direction(s)" in r.stderr
    few = {k: (v[:, :2] if k == "frames" else v[:2] if k in ("drive", "brightness", "lights/light_vectors") else v)
           for k, v in rec.data.items()}
    few["drive"] = few["drive"][:, :2]
    meta = dict(rec.meta, pattern_names=rec.meta["pattern_names"][:2])
    fewp = write_record(tmp_path / "few.h5", Record("capture", few, meta))
    with pytest.raises(UserError, match="span 2 independent"):
        reconstruct(fewp, store=tmp_path / "c", images=False)


def test_version_1_captures_with_zero_references_are_still_read(capture, tmp_path):
    path, rec = capture
    old = Record("capture", dict(rec.data, reference=np.zeros(rec.data["frames"].shape[1:], np.uint16)),
                 dict(rec.meta, has_reference=False))
    p = write_record(tmp_path / "v1.h5", old)
    with h5py.File(p, "r+") as f:
        f.attrs["iristac_schema_version"] = 1
    back = read_record(p, schema="capture")
    assert back.provenance["iristac_schema_version"] == 1
    r = reconstruct(p, solver="robust", store=tmp_path / "c", images=False)
    assert r.summary["normal_mean_error_deg"] < 1.0
    with pytest.raises(UserError, match="--ratio needs no-contact reference frames"):
        reconstruct(p, ratio=True, store=tmp_path / "c", images=False)
    with pytest.raises(UserError, match="--ratio needs no-contact reference frames"):
        reconstruct(path, ratio=True, store=tmp_path / "c", images=False)  # version 2: no dataset at all
    with h5py.File(p, "r+") as f:
        f.attrs["iristac_schema_version"] = 9
    with pytest.raises(StoreError, match="version 9 but this package reads version 1 or 2"):
        read_record(p)


def test_batch_takes_a_mask_too(capture, tmp_path):
    path, rec = capture
    np.save(tmp_path / "roi.npy", rec.data["mask"] & (np.arange(FRAME[1])[None, :] < 26))
    r = run_cli("batch", path, "--solver", "robust", "--mask", tmp_path / "roi.npy", "--cache", tmp_path / "c",
                "--json")
    assert r.returncode == 0, r.stderr
    item = json.loads(r.stdout)["items"][0]
    assert item["ok"] and 0 < item["result"]["valid_fraction"] < rec.data["mask"].mean()
    r = run_cli("batch", path, "--mask", tmp_path / "nope.png", "--cache", tmp_path / "c")
    assert r.returncode == 2 and "--mask" in r.stderr and "nope.png: no such file" in r.stderr
