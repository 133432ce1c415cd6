"""Every model ``calibrate`` fits reconstructs: ``reconstruct --solver far|near|lut|mlp`` through the real
CLI applies the calibration exactly as ``eval calibration`` does (the model's batched
``normal_maps``), with masks, confidences and printed markers filled in.

Real frames: the shared GelSight presses, a small split (presses 0-7 calibrate, 20-22 test).
Rendered: a synthetic sphere capture with truth.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from helpers import SHARED, run_cli

DATA = SHARED / "data" / "gelsight_ball_presses.npz"
needs_data = pytest.mark.skipif(not DATA.is_file(), reason=f"shared real frames not found at {DATA}")


@pytest.fixture(scope="module")
def real_split(tmp_path_factory):
    """(calibration.h5, test capture.h5, test capture with drawn markers, marker mask PNG)."""
    import cv2

    from calibration.calibrate import calibrate
    from calibration.importers import load_gelsight_npz
    from calibration.markers import draw_markers
    from pipeline.base.capture import Capture, write_capture
    from pipeline.base.threads import limit_threads

    d = tmp_path_factory.mktemp("real")
    cap = load_gelsight_npz(DATA)
    train, test = cap.select(slice(0, 8)), cap.select(slice(20, 23))
    with limit_threads(torch=1):
        res = calibrate(train, 2.0, cap.mm_per_px, ["far", "near", "lut", "mlp"], folds=2, refine_iterations=0,
                        model_options={"mlp": {"epochs": 60, "max_samples": 1500}})
    cal = res.save(d / "cal.h5")
    test_path = write_capture(d / "test.h5", test)
    frames, mask = draw_markers(np.asarray(test.frames))
    ref, _ = draw_markers(np.asarray(test.reference))
    marked = Capture(frames=frames, reference=ref, drive=test.drive, brightness=test.brightness,
                     mm_per_px=test.mm_per_px, meta=dict(test.meta))
    marked_path = write_capture(d / "marked.h5", marked)
    png = d / "markers.png"
    cv2.imwrite(str(png), mask.astype(np.uint8) * 255)
    return cal, test_path, marked_path, png, mask


def _reconstruct(capture, cal, solver, out, *extra):
    r = run_cli("reconstruct", capture, "--calibration", cal, "--solver", solver, "--out", out, "--no-images",
                "--cache", out / "cache", "--json", *extra)
    assert r.returncode == 0, r.stderr
    from pipeline.base.store import read_record

    return json.loads(r.stdout), read_record(out / "normals.h5", "normals"), read_record(out / "depth.h5", "depth")


def _reconstruct_api(capture, cal, solver, out, **options):
    """:func:`pipeline.workflows.reconstruct.reconstruct` in this process (what the CLI runs, without its
    start-up): ``(summary, normals record, depth record)``."""
    from pipeline.workflows.reconstruct import reconstruct

    res = reconstruct(capture, calibration=cal, solver=solver, out=out, store=out / "cache", images=False, **options)
    return res.summary, res.normals, res.depth


@needs_data
@pytest.mark.parametrize("solver", ["far", "near", "lut", "mlp"])
def test_every_model_reconstructs_real_frames_as_the_model_predicts(real_split, tmp_path, solver):
    from calibration.stored import load_models
    from pipeline.base.capture import read_capture

    cal, test_path, *_ = real_split
    summary, n_rec, d_rec = _reconstruct(test_path, cal, solver, tmp_path, "--drift", "none")
    cap = read_capture(test_path)
    frames, ref = cap.linear()
    maps = load_models(cal)[solver].normal_maps(frames, ref)
    np.testing.assert_array_equal(n_rec.data["mask"], maps.mask)
    np.testing.assert_allclose(n_rec.data["normals"], maps.normals, atol=1e-6)
    np.testing.assert_allclose(n_rec.data["confidence"], maps.confidence, atol=1e-6)
    assert n_rec.meta["confidence"] == maps.meta["confidence"] and summary["solver"] == solver
    assert 0.5 < summary["valid_fraction"] <= 1.0
    # Presses are bumps toward the camera: the depth at each press's peak is positive.
    assert (d_rec.data["height"].reshape(3, -1).max(axis=1) > 0.05).all()
    # By default each press's drift against the reference (fitted on the whole frame, trimmed) is
    # removed first: the model's prediction for the frames so corrected.
    from pipeline.normals.drift import STREAM_SAMPLES, fit_drift
    from pipeline.workflows.reconstruct import reconstruct

    res = reconstruct(test_path, calibration=cal, solver=solver, store=tmp_path / "auto", images=False)
    fixed = np.stack([fit_drift(f, ref, max_samples=STREAM_SAMPLES).remove(f) for f in frames])
    maps = load_models(cal)[solver].normal_maps(fixed, ref)
    assert res.summary["drift"] == res.normals.meta["drift"] == "gain_offset"
    np.testing.assert_array_equal(res.normals.data["mask"], maps.mask)
    np.testing.assert_allclose(res.normals.data["normals"], maps.normals, atol=1e-6)


@needs_data
def test_lut_reconstruct_equals_eval_calibration_ball_fit(real_split, tmp_path):
    """One code path: the heights ``eval calibration`` fits a ball to come from the same normals
    ``reconstruct --solver lut`` writes (the calibrated table with its position correction).
    ``eval`` removes each press's illumination drift first (fitted outside its circle), ``reconstruct`` too
    (fitted on the whole frame, trimmed); with both off the frames are the same."""
    from calibration.ballfit import ball_fit
    from calibration.detect import DetectOptions
    from calibration.evaluate import evaluate_calibration
    from calibration.models.lut import LookupTable
    from pipeline.base.capture import read_capture

    cal, test_path, *_ = real_split
    _, n_rec, _ = _reconstruct(test_path, cal, "lut", tmp_path, "--drift", "none")
    ev = evaluate_calibration(cal, test_path, 2.0, models=["lut"], refine_iterations=0, folds=2,
                              detect_options=DetectOptions(drift="none"))
    cap = read_capture(test_path)
    for k, press in enumerate(ev["ball_fit"]["lut"]["per_press"]):
        mine = ball_fit(n_rec.data["normals"][k], cap.mm_per_px, 2.0, mask=n_rec.data["mask"][k], level=0.5)
        assert mine["radius_mm"] == pytest.approx(press["radius_mm"], rel=1e-6, abs=1e-9)
    # ... and not from the plain table alone (what --solver lut read before).
    from pipeline.base.store import read_record

    arrays = {k.split("/", 2)[2]: v for k, v in read_record(cal, "calibration").data.items()
              if k.startswith("models/lut/")}
    assert "position_coef" in arrays
    frames, _ = cap.linear()
    g, ok = LookupTable.from_arrays(arrays).lookup(frames[:, 0])
    from pipeline.base.frames import gradients_to_normals

    plain = gradients_to_normals(g[..., 0], g[..., 1])
    both = ok & n_rec.data["mask"]
    assert np.abs(plain[both] - n_rec.data["normals"][both]).max() > 0.01


@needs_data
def test_markers_are_filled_masked_and_integrated_through(real_split, tmp_path):
    from calibration.stored import load_models
    from pipeline.base.capture import read_capture

    cal, _, marked_path, png, mask = real_split
    s, n_rec, d_rec = _reconstruct_api(marked_path, cal, "mlp", tmp_path / "png", markers=png, drift="none")
    assert s["markers"] == int(mask.sum()) > 50
    np.testing.assert_array_equal(n_rec.data["filled"], mask)
    assert not n_rec.data["mask"][:, mask].any()
    cap = read_capture(marked_path)
    frames, ref = cap.linear()
    maps = load_models(cal)["mlp"].normal_maps(frames, ref, markers=mask)
    np.testing.assert_allclose(n_rec.data["normals"], maps.normals, atol=1e-6)
    # The depth stage integrated through the filled pixels: they carry heights.
    assert d_rec.data["mask"][:, mask].all()
    # A light-field solver fills the frames before solving: the filled normals are not flat.
    s2, n2, _ = _reconstruct_api(marked_path, cal, "nearfield", tmp_path / "nf", markers=png)
    assert not n2.data["mask"][:, mask].any() and n2.meta["markers"] == int(mask.sum())
    assert np.abs(n2.data["normals"][:, mask, 2] - 1).max() > 0.01
    # --markers none: the same capture, markers unfilled and valid (dark dots solved as-is).
    s3, n3, _ = _reconstruct_api(marked_path, cal, "mlp", tmp_path / "none", markers="none")
    assert s3["markers"] == 0 and "filled" not in n3.data
    # A mask of the wrong size is one clear error naming the file.
    import cv2

    bad = tmp_path / "bad.png"
    cv2.imwrite(str(bad), np.zeros((10, 10), np.uint8))
    r = run_cli("reconstruct", marked_path, "--calibration", cal, "--solver", "mlp", "--out", tmp_path / "x",
                "--markers", bad, "--cache", tmp_path / "cache")
    assert r.returncode == 2 and "bad.png" in r.stderr and "Traceback" not in r.stderr


def test_models_reconstruct_a_rendered_sphere(tmp_path):
    """A rendered sphere with truth: the near-field and MLP models (the CLI's function), the error
    against the rendered normals small, and a model the calibration lacks one clear error."""
    from calibration.calibrate import calibrate
    from calibration.synthetic import synthetic_sphere_capture
    from pipeline.base.capture import write_capture
    from pipeline.base.threads import limit_threads

    cap, _ = synthetic_sphere_capture((48, 64), 8, num_leds=6, peak_dn=160, seed=3)
    with limit_threads(torch=1):
        res = calibrate(cap.select(slice(0, 6)), 1.5, cap.mm_per_px, ["near", "mlp"], folds=2, refine_iterations=0,
                        model_options={"mlp": {"epochs": 150, "max_samples": 2000}})
    cal = res.save(tmp_path / "cal.h5")
    test = cap.select(slice(6, 8))
    path = write_capture(tmp_path / "test.h5", test)
    errors = {}
    for solver in ("near", "mlp"):
        s, n_rec, _ = _reconstruct_api(path, cal, solver, tmp_path / solver)
        errors[solver] = s["normal_mean_error_deg"]
        assert n_rec.data["confidence"].shape == n_rec.data["mask"].shape
    assert errors["near"] < 3.0 and errors["mlp"] < 8.0, errors
    r = run_cli("reconstruct", path, "--calibration", cal, "--solver", "lut", "--out", tmp_path / "x",
                "--cache", tmp_path / "cache")
    assert r.returncode == 2 and "lookup table" in r.stderr and "Traceback" not in r.stderr
