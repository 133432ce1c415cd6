"""reconstruct(): capture + lights -> normals.h5 + depth.h5 (+ PNG, PLY) through the store, and its CLI."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from plyfile import PlyData

from helpers import run_cli
from pipeline.base.errors import UserError
from pipeline.base.store import StageStore, read_record, write_record
from pipeline.bench.recon_scene import scene_records
from pipeline.workflows.reconstruct import reconstruct
from support_recon import _one_torch_thread, render_sphere_scene  # noqa: F401


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("recon")
    s = render_sphere_scene((30, 40), 0.12, radius=2.0, depth=0.3, num_patterns=6, noise=1.0, bits=8, seed=4)
    cap, ill, cal = scene_records(s, num_presses=2)
    paths = {"capture": d / "capture.h5", "illumination": d / "illumination.h5", "calibration": d / "calibration.h5"}
    for name, rec in (("capture", cap), ("illumination", ill), ("calibration", cal)):
        write_record(paths[name], rec)
    paths["dir"] = d
    return paths


def test_nearfield_from_illumination_writes_everything(files, tmp_path):
    store = StageStore(tmp_path / "cache")
    res = reconstruct(files["capture"], illumination=files["illumination"], solver="nearfield", integrator="dst",
                      out=tmp_path / "out", store=store, save="all")
    s = res.summary
    assert set(s) >= {"solver", "integrator", "seconds", "valid_fraction", "normal_mean_error_deg", "depth_rmse_mm"}
    assert s["valid_fraction"] == 1.0 and s["normal_mean_error_deg"] < 1.0 and s["depth_rmse_mm"] < 0.02
    n = read_record(tmp_path / "out" / "normals.h5", schema="normals")
    d = read_record(tmp_path / "out" / "depth.h5", schema="depth")
    assert n.data["normals"].shape == (2, 30, 40, 3) and n.data["albedo"].shape == (2, 30, 40, 3)
    assert d.data["height"].shape == (2, 30, 40) and d.meta["integrator"] == "dst"
    assert d.data["height"].max() > 0.25  # the bump is toward the camera
    png = cv2.imread(str(tmp_path / "out" / "normals_k000.png"), cv2.IMREAD_UNCHANGED)
    assert png.shape == (30, 40, 3)
    # A flat-gel corner pixel encodes n = (0, 0, 1) -> RGB (128, 128, 255), stored BGR on disk.
    assert png[0, 0, ::-1].tolist() == [128, 128, 255]
    ply = PlyData.read(str(tmp_path / "out" / "depth_k001.ply"))
    assert ply["vertex"].count == 30 * 40
    # Second call: both stages come from the store.
    again = reconstruct(files["capture"], illumination=files["illumination"], solver="nearfield", integrator="dst",
                        store=store, save="all")
    assert again.summary["cached"] and not res.summary["cached"]
    np.testing.assert_array_equal(again.depth.data["height"], d.data["height"])
    # force: solved again although the store has it (the old entry replaced only when the new is whole).
    forced = reconstruct(files["capture"], illumination=files["illumination"], solver="nearfield", integrator="dst",
                         store=store, save="all", force=True)
    assert not forced.summary["cached"] and forced.summary["method"] != "cached"
    np.testing.assert_array_equal(forced.depth.data["height"], d.data["height"])


def test_matching_colours_needs_both_references(files, tmp_path):
    """Colours are matched to the reference a light model stores (the LUT's, the MLP's): an
    illumination model stores none, and the error says which file and what is missing."""
    with pytest.raises(UserError, match=r"illumination.*no-contact reference .*'nearfield'.*stores"):
        reconstruct(files["capture"], illumination=files["illumination"], solver="nearfield", store=tmp_path / "c",
                    match_colours=True, images=False)


def test_far_field_gap_and_calibration_lights(files, tmp_path):
    store = StageStore(tmp_path / "cache")
    near = reconstruct(files["capture"], calibration=files["calibration"], solver="nearfield", store=store)
    far = reconstruct(files["capture"], calibration=files["calibration"], solver="lstsq", store=store)
    assert near.summary["normal_mean_error_deg"] < 1.0
    assert far.summary["normal_mean_error_deg"] > 3 * near.summary["normal_mean_error_deg"]


def test_cli_json(files, tmp_path, solver="robust", integrator="sparse"):
    r = run_cli("reconstruct", files["capture"], "--illumination", files["illumination"], "--solver", solver,
                "--integrator", integrator, "--out", tmp_path / "o", "--cache", tmp_path / "c", "--json",
                "--no-images")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["solver"] == solver and out["integrator"] == integrator
    assert out["normal_mean_error_deg"] < 1.0 and 0 <= out["valid_fraction"] <= 1
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["contact.h5", "depth.h5", "normals.h5"]
    # Links to the store's entries, not copies.
    assert all((tmp_path / "o" / f).stat().st_nlink == 2 for f in ("contact.h5", "depth.h5", "normals.h5"))


def test_threads_take_the_batch_fast_paths(files, tmp_path):
    """``--threads 0`` (every core): nearfield by the batch kernel, frames in parallel, dst by
    FastDST.integrate_batch; the results of one thread, bit for bit (the same kernels)."""
    from pipeline.cli import build_parser

    assert build_parser().parse_args(["reconstruct", "c.h5", "--out", "o", "--threads", "0"]).threads == 0
    one = reconstruct(files["capture"], illumination=files["illumination"], solver="nearfield", store=tmp_path / "a")
    every = reconstruct(files["capture"], illumination=files["illumination"], solver="nearfield",
                        store=tmp_path / "b", threads=None)
    assert every.normals.meta["method"] == "fast" and one.normals.meta["method"] == "fast"
    assert every.summary["method"] == "fast"
    np.testing.assert_array_equal(every.normals.data["mask"], one.normals.data["mask"])
    np.testing.assert_allclose(every.normals.data["normals"], one.normals.data["normals"], atol=3e-5)
    np.testing.assert_allclose(every.depth.data["height"], one.depth.data["height"], atol=1e-5)


def test_cli_errors_are_one_line(files, tmp_path):
    r = run_cli("reconstruct", files["dir"] / "missing.h5", "--out", tmp_path)
    assert r.returncode == 2 and "missing.h5" in r.stderr and "Traceback" not in r.stderr
    with pytest.raises(UserError, match="no light model"):
        reconstruct(files["capture"], store=tmp_path / "c")
    with pytest.raises(UserError, match="nearfield needs per-pixel lights"):
        cap, _, cal = scene_records(render_sphere_scene((6, 8), 0.5, num_patterns=3))
        del cal.data["light_field"]
        reconstruct(cap, calibration=cal, solver="nearfield", store=tmp_path / "c2")
    with pytest.raises(UserError, match="lookup table"):
        reconstruct(files["capture"], calibration=files["calibration"], solver="lut", store=tmp_path / "c3")


def test_compile_matches_the_eager_solver(files, tmp_path):
    """``compile=True`` (``--compile``: the fused far-field kernel under torch.compile) gives the
    eager solver's normals to float32 rounding, with no fallback warning (in this process: the
    CLI only passes the flag on, and a subprocess would pay torch.compile's start-up again)."""
    import warnings

    outs = {}
    for compiled in (False, True):
        d = tmp_path / ("c" if compiled else "e")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = reconstruct(files["capture"], calibration=files["calibration"], solver="lstsq", out=d / "o",
                              store=d / "cache", images=False, compile=compiled)
        fallback = [str(w.message) for w in caught if "torch.compile of the far-field solver failed" in str(w.message)]
        assert not fallback, fallback
        outs[compiled] = res.normals
    np.testing.assert_allclose(outs[True].data["normals"], outs[False].data["normals"], atol=1e-5)
    np.testing.assert_array_equal(outs[True].data["mask"], outs[False].data["mask"])


def test_bench_reconstruct_reports_eager_and_compiled_pipelines():
    r = run_cli("bench", "reconstruct", "--sizes", "64x48", "--repeats", "1", "--sections", "tactile", "--json",
                timeout=300)
    assert r.returncode == 0, r.stderr
    size = json.loads(r.stdout)["sizes"][0]
    assert set(size["pipelines"]) == {"lstsq+dst (eager)", "lstsq+fc (eager)", "lstsq+dst (compiled)",
                                      "lstsq+fc (compiled)"}
    assert size["solvers"]["lstsq (far field, compiled)"]["mean_deg"] == pytest.approx(
        size["solvers"]["lstsq (far field)"]["mean_deg"], abs=1e-3)
    assert all(v["fps"] > 0 for v in size["pipelines"].values())
