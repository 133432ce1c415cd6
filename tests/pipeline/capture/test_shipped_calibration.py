"""The calibration shipped with the DIGIT profile (pipeline/capture/shipped.py): it loads under
today's calibration.h5 schema and models, it is small, it ships (package data, licence note),
and the figures it carries are a measurement that met its target; ``live`` and ``reconstruct
--profile digit`` use it with no --calibration, say so, and match another unit's colours to it."""

from __future__ import annotations

import fnmatch
import json
import re

import numpy as np
import pytest

from helpers import REPO, run_cli
from pipeline.capture.sensor_profiles import PROFILES_DIR, load_profile
from pipeline.capture.shipped import shipped_calibration_path, shipped_info, shipped_note

PATH = shipped_calibration_path("digit")
GAIN = (0.9, 1.1, 1.0)  # another unit's LEDs, RGB
META = {"source": "test", "pattern_names": ["all"], "sensor_profile": "digit"}


def test_shipped_file_loads_under_the_current_schema_and_models():
    from calibration.models.mlp import MLPModel
    from calibration.stored import load_models
    from pipeline.base.store import read_record

    assert PATH is not None and PATH.parent == PROFILES_DIR
    rec = read_record(PATH, "calibration")  # validated against data_schemas/stages/calibration.json
    prof = load_profile("digit")
    assert rec.meta["mm_per_px"] == prof.mm_per_px and rec.meta["ball_radius_mm"] == prof.ball_radius_mm
    assert rec.meta["models"] == ["mlp"] and rec.meta["quality_gate"]["passed"] is True
    mlp = load_models(PATH)["mlp"]
    assert isinstance(mlp, MLPModel) and len(mlp.nets) == prof.calibration_mlp_members
    ref = mlp.reference
    assert ref.shape == (1, prof.resolution[1], prof.resolution[0], 3)
    maps = mlp.normal_maps(ref[None, :, 200:264, 200:264], ref[:, 200:264, 200:264])  # the gel, untouched: flat
    assert maps.mask.all() and np.median(maps.normals[..., 2]) > 0.99


def test_shipped_file_is_small_and_ships_with_its_licence():
    assert PATH.stat().st_size < 2_000_000
    line = re.search(r'^"pipeline\.capture" = (\[.*\])$', (REPO / "pyproject.toml").read_text(encoding="utf-8"), re.M)
    shipped = json.loads(line.group(1))  # the package data of pipeline.capture
    for f in (PATH, PROFILES_DIR / shipped_info("digit")["licence_file"]):
        assert any(fnmatch.fnmatch(str(f.relative_to(REPO / "pipeline" / "capture")), pat) for pat in shipped), f
    text = (PROFILES_DIR / shipped_info("digit")["licence_file"]).read_text(encoding="utf-8")
    assert "MIT License" in text and "Copyright (c) 2021 CMURoboTouch" in text and "vocdex/Taxim" in text


def test_shipped_figures_are_the_measurement_and_meet_the_target():
    info = shipped_info("digit")
    orig, alt = info["original"], info["altered"]
    assert orig["presses"] == alt["presses"] == 10 and orig["accepted"] >= 9 and alt["accepted"] >= 9
    assert 2 < orig["mean_deg"] < 8 and abs(alt["mean_deg"] - orig["mean_deg"]) <= 3.0
    assert "colour gain" in alt["alteration"] and "turned" in alt["alteration"]
    note = shipped_note("digit")
    assert f"expect about {alt['mean_deg']:.1f} deg" in note and "MIT licence" in note and "Taxim" in note
    assert shipped_calibration_path("gelsight-mini") is None


def _video(path, frames_rgb):
    """An FFV1 video (lossless) of RGB frames, as OpenCV writes them (BGR)."""
    import cv2

    h, w = frames_rgb.shape[1:3]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (w, h))
    assert out.isOpened()
    for f in frames_rgb:
        out.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    out.release()
    return path


def _press(ref: np.ndarray, centre=(320, 240), radius=60.0) -> np.ndarray:
    """The reference (H, W, 3) with a shaded disc: a press's colour change, roughly."""
    y, x = np.mgrid[0:ref.shape[0], 0:ref.shape[1]]
    d2 = ((y - centre[0]) ** 2 + (x - centre[1]) ** 2) / radius ** 2
    bump = np.where(d2 < 1, np.sqrt(np.clip(1 - d2, 0, 1)), 0)[..., None] * np.array([25.0, -15.0, 10.0])
    return np.clip(ref + bump * ((x - centre[1]) / radius)[..., None], 0, 255)


def _gains(frames) -> str:
    """The colour gains the CLIs print for frames whose first is the no-contact one: about 1 / GAIN."""
    from pipeline.capture.shipped import colour_gain, shipped_reference

    g = colour_gain(frames[0], shipped_reference(PATH))
    np.testing.assert_allclose(g, 1 / np.array(GAIN), rtol=0.01)
    return " / ".join(f"{v:.3f}" for v in g)


@pytest.fixture(scope="module")
def digit_frames():
    """The shipped reference as a DIGIT's images (640 x 480 portrait, RGB uint8): no contact, then two presses."""
    from calibration.stored import load_models

    ref = load_models(PATH)["mlp"].reference[0].astype(np.float64)
    return np.stack([ref, _press(ref), _press(ref, (200, 300), 50.0)]).round().astype(np.uint8)


def test_live_profile_digit_uses_the_shipped_calibration(digit_frames, tmp_path):
    # Another unit: other LED colours (the colours are matched back from its first frame). The
    # DIGIT streams 640 x 480 landscape; its profile turns it portrait.
    other = np.clip(np.rint(digit_frames * np.array(GAIN)), 0, 255).astype(np.uint8)
    video = _video(tmp_path / "digit.avi", np.stack([np.rot90(f, k=-1) for f in other]))
    r = run_cli("live", "--profile", "digit", "--camera", video, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "no --calibration given: using the shipped DIGIT calibration" in r.stderr
    assert "on another unit expect about" in r.stderr
    assert f"colours matched to the shipped calibration's from the first frame (gain per channel {_gains(other)})" \
        in r.stderr
    # The first frame is the session's no-contact reference (another unit's: not the shipped one).
    assert r.stdout.startswith("2 results (trichromatic, mlp "), r.stdout


def test_reconstruct_profile_digit_uses_the_shipped_calibration(digit_frames, tmp_path):
    from pipeline.base.capture import Capture, write_capture

    other = np.clip(np.rint(digit_frames * np.array(GAIN)), 0, 255).astype(np.uint8)
    cap = Capture(frames=other[1:, None], reference=other[:1], drive=np.eye(3, dtype=np.float32)[None],
                  brightness=np.ones(1, np.float32), mm_per_px=0.0266, meta=META)
    path = write_capture(tmp_path / "cap.h5", cap)
    r = run_cli("reconstruct", path, "--profile", "digit", "--out", tmp_path / "out", "--no-images",
                "--cache", tmp_path / "cache", timeout=120)
    assert r.returncode == 0, r.stderr
    assert "iristac reconstruct: no --calibration given: using the shipped DIGIT calibration" in r.stderr
    assert ("colours matched to the shipped calibration's from the capture's no-contact frame (gain per channel "
            f"{_gains(other)})") in r.stderr
    assert r.stdout.startswith("mlp + dst: 100.0% valid pixels"), r.stdout


def test_a_light_model_of_the_users_wins(capsys):
    """Where the user gives --calibration or --illumination, or the profile ships none, nothing changes."""
    from pipeline.cli._common import shipped_calibration

    assert shipped_calibration("live", "digit", "cal.h5", None) is None
    assert shipped_calibration("reconstruct", "digit", None, "ill.h5") is None
    assert shipped_calibration("live", "gelsight-mini", None, None) is None
    assert shipped_calibration("live", None, None, None) is None
    assert capsys.readouterr().err == ""
    assert shipped_calibration("live", "digit", None, None) == PATH
    assert "iristac live: no --calibration given: using the shipped DIGIT calibration" in capsys.readouterr().err


def test_reconstruct_matches_another_units_colours_as_it_streams(digit_frames, tmp_path):
    """``reconstruct(..., profile="digit")`` brings another unit's frames to the shipped unit's
    colours from its no-contact frame (no copy of the capture): its normals are the original
    unit's to rounding, unmatched ones are not, and the gain is part of the normals' key."""
    from pipeline.base.capture import Capture, write_capture
    from pipeline.workflows.reconstruct import reconstruct

    def capture(frames, name):
        cap = Capture(frames=frames[1:, None], reference=frames[:1], drive=np.eye(3, dtype=np.float32)[None],
                      brightness=np.ones(1, np.float32), mm_per_px=0.0266, meta=META)
        return write_capture(tmp_path / name, cap)

    # The no-contact frame and one press: each reconstruct solves one 640 x 480 frame by the MLP.
    other = np.clip(np.rint(digit_frames[:2] * np.array(GAIN)), 0, 255).astype(np.uint8)
    mine, theirs = capture(digit_frames[:2], "mine.h5"), capture(other, "other.h5")
    store = tmp_path / "cache"
    base = reconstruct(mine, calibration=PATH, solver="mlp", store=store, images=False)
    matched = reconstruct(theirs, profile="digit", store=store, images=False)
    plain = reconstruct(theirs, profile="digit", match_colours=False, store=store, images=False)
    assert "colour_gain" not in base.summary and "colour_gain" not in plain.summary
    np.testing.assert_allclose(matched.summary["colour_gain"], 1 / np.array(GAIN), rtol=0.01)
    assert matched.summary["shipped_calibration"] == str(PATH) and matched.summary["solver"] == "mlp"
    assert not plain.summary["cached"]  # another key: not the matched run's entry

    def error_deg(res):
        n, ref = np.asarray(res.normals.data["normals"]), np.asarray(base.normals.data["normals"])
        m = np.asarray(res.normals.data["mask"]) & np.asarray(base.normals.data["mask"])
        cos = np.clip(np.einsum("...c,...c->...", n, ref), -1, 1)
        return float(np.degrees(np.arccos(cos[m])).mean())

    # Measured: 0.03 deg matched (uint8 rounding twice), 0.60 deg unmatched.
    assert error_deg(matched) < 0.1 and error_deg(plain) > 5 * error_deg(matched), (error_deg(matched), error_deg(plain))
    assert reconstruct(theirs, profile="digit", store=store, images=False).summary["cached"]


def test_batch_matches_colours_in_its_range_tasks(digit_frames, tmp_path):
    """``batch --match-colours``: each recording's own gain, applied in the range task that the
    worker processes run on its frame ranges; the entry is the one ``reconstruct(profile=...)`` writes."""
    from pipeline.base.capture import Capture, write_capture
    from pipeline.workflows.batch import batch_reconstruct
    from pipeline.workflows.reconstruct import reconstruct

    other = np.clip(np.rint(digit_frames * np.array(GAIN)), 0, 255).astype(np.uint8)
    # Two presses: one frame range (ranges hold 16 frames at least), which the task pool runs in this
    # process through the same range task the worker processes run.
    frames = other[1:]
    cap = Capture(frames=frames[:, None], reference=other[:1], drive=np.eye(3, dtype=np.float32)[None],
                  brightness=np.ones(1, np.float32), mm_per_px=0.0266, meta=META)
    path = write_capture(tmp_path / "other.h5", cap)
    store = tmp_path / "cache"
    ref = reconstruct(path, profile="digit", store=store, images=False, save="none")
    before = np.array(ref.normals.data["normals"])
    items = batch_reconstruct([str(path)], calibration=str(PATH), solver="mlp", store=str(store), workers=2,
                              match_colours=True, force=True)
    assert items[0].ok and items[0].frames_solved == 2, items[0]
    again = reconstruct(path, profile="digit", store=store, images=False, save="none")
    assert again.summary["cached"]  # the entry batch rewrote: same key, gain and all
    assert items[0].result["normals_key"] in str(again.normals.path)
    np.testing.assert_allclose(np.asarray(again.normals.data["normals"]), before, atol=1e-5)
