"""Sensor profiles (validated YAML) and finding a camera by name in a /dev/v4l/by-id folder of real
symlinks; the profile in import images, calibrate and a camera's frames."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.base.errors import UserError
from pipeline.capture.camera_names import find_camera, list_cameras, resolve_camera_source
from pipeline.capture.sensor_profiles import ProfileCamera, capture_defaults, list_profiles, load_profile


@pytest.fixture
def by_id(tmp_path):
    """A by-id folder as udev makes it: names -> ../../videoN, two nodes per camera."""
    dev = tmp_path / "dev"
    (dev / "v4l" / "by-id").mkdir(parents=True)
    for n in range(6):
        (dev / f"video{n}").touch()
    links = {"usb-GelSight_Inc._GelSight_Mini_R0B_28J2-CWXU-video-index0": "video2",
             "usb-GelSight_Inc._GelSight_Mini_R0B_28J2-CWXU-video-index1": "video3",
             "usb-Facebook_DIGIT_D20025-video-index0": "video4",
             "usb-Facebook_DIGIT_D20026-video-index0": "video0",
             "usb-Generic_HD_Webcam_200901010001-video-index0": "video5"}
    for name, target in links.items():
        os.symlink(os.path.join("..", "..", target), dev / "v4l" / "by-id" / name)
    return dev / "v4l" / "by-id"


def test_find_camera_by_name(by_id):
    m = find_camera("GelSight Mini", by_id)
    assert m.index == 2 and m.device == os.path.realpath(by_id.parent.parent / "video2")  # index0, not metadata
    assert find_camera("digit*26*", by_id).index == 0  # a glob picks one of two DIGITs
    assert find_camera("d20025", by_id).index == 4
    assert len(list_cameras(by_id)) == 4
    with pytest.raises(UserError, match="matches 2 cameras.*D20025.*D20026"):
        find_camera("DIGIT", by_id)
    with pytest.raises(UserError, match="no camera of that name.*Generic_HD_Webcam"):
        find_camera("RealSense", by_id)
    with pytest.raises(UserError, match="no cameras named"):
        find_camera("DIGIT", by_id / "missing")
    assert resolve_camera_source("gelsight mini", by_id).endswith("video2")
    assert resolve_camera_source("3", by_id) == 3 and resolve_camera_source("clip.mp4", by_id) == "clip.mp4"


def test_shipped_profiles_are_valid_and_bad_ones_are_named(tmp_path):
    assert list_profiles() == ["digit", "gelsight-mini", "iristac-ring"]
    digit, mini = load_profile("digit"), load_profile("gelsight-mini")
    assert digit.mm_per_px == 0.0266 and digit.ball_radius_mm == 3.0 and digit.resolution == (480, 640)
    assert mini.to_image(np.zeros((2464, 3280, 3), np.uint8)).shape == (240, 320, 3)
    assert load_profile("iristac-ring").mode == "point"
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nmake: y\nresolution: {width: 32, height: 24}\nmm_per_px: 0.1\nball_radius_mm: 1\n"
                   "colour: red\n")
    with pytest.raises(UserError, match="bad.yaml.*colour"):
        load_profile(bad)
    bad.write_text("name: x\nmake: y\nresolution: {width: 32, height: 24}\nmm_per_px: -1\nball_radius_mm: 1\n")
    with pytest.raises(UserError, match="bad.yaml.*mm_per_px"):
        load_profile(bad)
    # The DIGIT's calibration removes a smooth drift field (measured: docs/calibration.md, "Drift"); the
    # others keep the default. A drift model the code does not know is the file's error.
    assert digit.calibration_drift == "field" and mini.calibration_drift is None
    bad.write_text("name: x\nmake: y\nresolution: {width: 32, height: 24}\nmm_per_px: 0.1\nball_radius_mm: 1\n"
                   "calibration_drift: wobble\n")
    with pytest.raises(UserError, match="bad.yaml.*calibration_drift"):
        load_profile(bad)
    # The DIGIT's calibration fits three nets (docs/calibration.md, point 11); an ensemble of none is the file's error.
    assert digit.calibration_mlp_members == 3 and mini.calibration_mlp_members is None
    bad.write_text("name: x\nmake: y\nresolution: {width: 32, height: 24}\nmm_per_px: 0.1\nball_radius_mm: 1\n"
                   "calibration_mlp_members: 0\n")
    with pytest.raises(UserError, match="bad.yaml.*calibration_mlp_members"):
        load_profile(bad)


def test_profile_drift_choices_are_the_drift_models():
    """One owner: the profile's and the capture's schema choices are pipeline.normals.drift.DRIFT_MODELS."""
    import json

    import data_schemas
    from pipeline.normals.drift import DRIFT_MODELS

    schema = json.loads((Path(data_schemas.__file__).parent / "configs" / "sensor.json").read_text())
    assert tuple(schema["properties"]["calibration_drift"]["enum"]) == DRIFT_MODELS
    capture = json.loads((Path(data_schemas.__file__).parent / "stages" / "capture.json").read_text())
    assert tuple(capture["properties"]["attrs"]["properties"]["calibration_drift"]["enum"]) == DRIFT_MODELS


def _profile_file(tmp_path):
    p = tmp_path / "tiny.yaml"
    p.write_text("name: tiny\nmake: test\ncamera: Tiny Cam\nstream: {width: 64, height: 48}\n"
                 "crop: {x: 8, y: 4, width: 48, height: 36}\nrotate: 90\nresolution: {width: 18, height: 24}\n"
                 "mm_per_px: 0.2\nball_radius_mm: 1.5\nmode: trichromatic\n")
    return p


def test_stream_frames_are_cropped_rotated_resized(tmp_path):
    prof = load_profile(_profile_file(tmp_path))
    frame = np.zeros((48, 64, 3), np.uint8)
    frame[4:40, 8:56] = 100  # the crop
    frame[4:40, 8:20, 0] = 250  # its left part red: after a counter-clockwise turn, the bottom
    img = prof.to_image(frame)
    assert img.shape == (24, 18, 3) and img[-1, :, 0].min() > 200 and img[0, :, 0].max() < 150
    assert prof.fit_frames(np.zeros((2, 1, 24, 18, 3))).shape == (2, 1, 24, 18, 3)  # already the size: kept
    with pytest.raises(UserError, match="50 x 40 px.*expects 18 x 24"):
        prof.fit_frames(np.zeros((40, 50, 3)), "x")


def test_profile_in_import_calibrate_and_a_camera(tmp_path):
    """import images --profile converts stream-size frames and takes the pitch and ball from it;
    calibrate's defaults come from it; a video of stream frames through ProfileCamera."""
    from calibration.image_import import load_images
    from pipeline.base.capture import write_capture
    from pipeline.capture.camera import OpenCVCamera

    prof_path = _profile_file(tmp_path)
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    stream = rng.integers(0, 200, (3, 48, 64, 3), dtype=np.uint8)
    stream[1, 20:30, 25:35] = 255  # presses in different places; frame 0 is the reference
    stream[2, 10:20, 30:40] = 255
    stream[1:] = np.where(stream[1:] == 255, 255, stream[0])
    for i, f in enumerate(stream):
        cv2.imwrite(str(folder / f"f{i}.png"), f[..., ::-1])
    cap, rep = load_images(folder, profile=prof_path, reference="f0")
    assert cap.frames.shape == (2, 1, 24, 18, 3) and cap.mm_per_px == 0.2 and cap.meta["ball_radius_mm"] == 1.5
    assert rep["profile"] == "tiny" and cap.meta["sensor_profile"] == "tiny" and "calibration_drift" not in cap.meta
    np.testing.assert_array_equal(cap.reference[0], load_profile(prof_path).to_image(stream[0]))
    write_capture(tmp_path / "c.h5", cap)
    assert capture_defaults(prof_path, tmp_path / "c.h5") == (1.5, 0.2)
    assert capture_defaults(prof_path, tmp_path / "c.h5", 2.0) == (2.0, 0.2)
    with pytest.raises(UserError, match="18 x 24.*digit.*480 x 640"):
        capture_defaults("digit", tmp_path / "c.h5")
    video = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (64, 48))
    for f in stream:
        w.write(f[..., ::-1])
    w.release()
    with pytest.warns(Warning):  # a video file has no exposure controls to lock
        cam = ProfileCamera(OpenCVCamera(str(video)), prof_path)
        cam.open()
    try:
        got = cam.read()
        assert cam.shape == (24, 18) and got.image.shape == (24, 18, 3) and cam.is_file and "tiny" in str(cam)
        np.testing.assert_array_equal(got.image, load_profile(prof_path).to_image(stream[0]))
    finally:
        cam.close()


def test_a_profile_files_drift_model_travels_with_the_capture(tmp_path):
    """A user's profile file is not found by its name later: import records its drift model and MLP
    ensemble size, and calibrate (no --profile) uses them unless told otherwise; a bad recorded
    value is named on reading."""
    import h5py

    from calibration.calibrate import capture_detect_options, capture_model_options, model_factories
    from calibration.image_import import load_images
    from pipeline.base.capture import read_capture, write_capture

    prof_path = _profile_file(tmp_path)
    prof_path.write_text(prof_path.read_text() + "calibration_drift: offset\ncalibration_mlp_members: 2\n")
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 200, (3, 24, 18, 3), dtype=np.uint8)
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"f{i}.png"), f[..., ::-1])
    cap, _ = load_images(folder, profile=prof_path, reference="f0")
    assert cap.meta["calibration_drift"] == "offset"
    write_capture(tmp_path / "c.h5", cap)
    assert capture_detect_options(read_capture(tmp_path / "c.h5")).drift == "offset"
    back = read_capture(tmp_path / "c.h5")
    assert capture_model_options(back) == {"mlp": {"members": 2}}
    assert model_factories(["mlp"], back, None, 255.0, None)["mlp"]().members == 2
    # What the caller says wins over the profile (calibrate --mlp-members 1, or model_options).
    assert model_factories(["mlp"], back, None, 255.0, {"mlp": {"members": 1}})["mlp"]().members == 1
    # A capture naming a built-in profile but recording no size (imported before it was recorded) gets the profile's.
    assert capture_model_options(dataclasses.replace(back, meta={"sensor_profile": "digit"})) == {"mlp": {"members": 3}}
    with h5py.File(tmp_path / "c.h5", "r+") as f:
        f.attrs["calibration_drift"] = "wobble"
    with pytest.raises(Exception, match="calibration_drift") as err:
        read_capture(tmp_path / "c.h5")
    assert "c.h5" in str(err.value)
    write_capture(tmp_path / "d.h5", cap)
    with h5py.File(tmp_path / "d.h5", "r+") as f:
        f.attrs["calibration_mlp_members"] = 0
    with pytest.raises(Exception, match="calibration_mlp_members") as err:
        read_capture(tmp_path / "d.h5")
    assert "d.h5" in str(err.value)
    # Through the CLI: a bad value in a profile file or in a capture is one line naming the file and
    # the key, and the file the command would have written is left as it was.
    from helpers import run_cli

    kept = tmp_path / "kept.h5"
    kept.write_bytes(b"saved before")
    bad_prof = tmp_path / "bad.yaml"
    bad_prof.write_text(prof_path.read_text().replace("calibration_mlp_members: 2", "calibration_mlp_members: 0"))
    for args in (("import", "images", folder, "--profile", bad_prof, "--reference", "f0", "--out", kept),
                 ("calibrate", tmp_path / "d.h5", "--ball-radius", "1.5", "--out", kept)):
        r = run_cli(*args)
        assert r.returncode == 2 and "calibration_mlp_members" in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert ("bad.yaml" if args[0] == "import" else "d.h5") in r.stderr, r.stderr
        assert kept.read_bytes() == b"saved before"


def test_import_without_a_profile_names_the_profile_of_that_size(tmp_path):
    """Images of a built-in profile's size imported without --profile: the import says which
    profile has that size (its calibration settings, the DIGIT's drift model, come with it)."""
    from helpers import run_cli

    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(1)
    for i in range(3):
        cv2.imwrite(str(folder / f"f{i}.png"), rng.integers(0, 200, (640, 480, 3), dtype=np.uint8))
    r = run_cli("import", "images", folder, "--out", tmp_path / "a.h5", "--mm-per-px", "0.03", "--reference", "f0")
    assert r.returncode == 0 and "'digit' sensor profile" in r.stdout and "--profile digit" in r.stdout, r.stderr
    assert "comparing" not in r.stderr  # the reference was named: no comparison, nothing to wait for
    r = run_cli("import", "images", folder, "--out", tmp_path / "b.h5", "--profile", "digit", "--reference", "f0")
    assert r.returncode == 0 and "sensor profile" not in r.stdout, r.stderr
