"""The virtual sensor (sim.virtual_sensor): exact truth, effects only when asked for, drift as
stated, and files the import/calibrate path reads."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.detect import detect_contacts
from calibration.importers import load_images
from pipeline.base.capture import read_capture
from sim import sensor_effects, virtual_sensor
from sim.virtual_sensor import SENSOR_EFFECTS, VirtualSensor, random_sensor, render_sensor, write_sensor_capture

SMALL = (60, 80)


@pytest.fixture(scope="module")
def plain():
    """No optional effect, no noise: the frames are the renderer's, quantized."""
    s = random_sensor(11, shape=SMALL, num_presses=3, effects="none", border_fraction=0.34)
    return s, render_sensor(s)


def test_truth_circles_heights_normals_are_exact(plain):
    s, out = plain
    t = out.truth
    h, w = SMALL
    rows, cols = np.mgrid[0:h, 0:w]
    R = s.ball_radius_mm
    for k in range(s.num_presses):
        (x, y), a = t.center_xy[k], t.radius_px[k]
        d2 = ((cols - x) ** 2 + (rows - y) ** 2) * s.mm_per_px ** 2
        inside = d2 < (a * s.mm_per_px) ** 2
        # the contact mask is the circle; the height is the ball's cap, the normal the sphere's
        assert np.array_equal(t.contact[k], inside)
        depth = R - np.sqrt(R * R - (a * s.mm_per_px) ** 2)
        cap = np.where(inside, np.sqrt(np.maximum(R * R - d2, 0)) - (R - depth), 0)
        np.testing.assert_allclose(t.height[k], cap, atol=1e-5)
        nz = np.where(inside, np.sqrt(np.maximum(R * R - d2, 0)) / R, 1.0)
        np.testing.assert_allclose(t.normals[k][..., 2], nz, atol=1e-5)
        # x grows with the column, y (recon) against the row
        sel = inside & (cols > x + 1)
        assert np.all(t.normals[k][..., 0][sel] > 0)
    assert t.touches_border.sum() == 1  # one press of three cut by the border (border_fraction 0.34)


def test_detected_circles_agree_with_truth_convention(plain):
    s, out = plain
    cap = out.capture
    circles = detect_contacts(cap.frames, cap.reference, s.ball_radius_px)
    for c, (x, y), r, border in zip(circles, out.truth.center_xy, out.truth.radius_px, out.truth.touches_border):
        if border:
            continue
        assert c.accepted, c.reason
        assert np.hypot(c.center_xy[0] - x, c.center_xy[1] - y) < 1.5
        assert abs(c.radius_px - r) < 1.5


def test_disabled_effects_are_not_computed(monkeypatch):
    def boom(*_a, **_k):
        raise AssertionError("a disabled effect was computed")

    for name in ("marker_coverage", "drift_field", "drift_basis", "apply_drift", "column_stripes", "jpeg_roundtrip"):
        monkeypatch.setattr(sensor_effects, name, boom)
    s = random_sensor(2, shape=(24, 32), num_presses=1, effects="none")
    out = render_sensor(s.replace(read_noise_dn=0.0))
    assert out.computed == [] and out.jpeg_bytes is None
    assert out.truth.markers is None and np.all(out.truth.drift_gain == 1)


@pytest.mark.parametrize("effect", SENSOR_EFFECTS)
def test_each_effect_alone_is_computed_and_changes_the_frames(effect, plain):
    s = random_sensor(4, shape=(24, 32), num_presses=1, effects=[effect])
    out = render_sensor(s)
    assert out.computed == (["markers", effect] if effect == "marker_motion" else [effect])  # moved dots need dots
    base = render_sensor(random_sensor(4, shape=(24, 32), num_presses=1, effects="none"))
    assert np.any(out.capture.frames != base.capture.frames)


def test_drift_is_what_the_truth_says():
    """A drifted press is gain * field * (undrifted press) + offset, to the 8-bit rounding."""
    s = random_sensor(5, shape=SMALL, num_presses=2, effects=["drift_gain", "drift_offset", "drift_field"])
    drifted = render_sensor(s)
    clean = render_sensor(s.replace(drift_gain=0.0, drift_offset_dn=0.0, drift_field=0.0))
    np.testing.assert_array_equal(drifted.capture.reference, clean.capture.reference)  # the reference has none
    t = drifted.truth
    for k in range(2):
        assert 0.85 <= t.drift_gain[k].min() and t.drift_gain[k].max() <= 1.15 and np.abs(t.drift_offset[k]).max() <= 30
        field = t.drift_field(k)
        assert 0 < np.abs(field - 1).max() <= 0.08 + 1e-6
        want = sensor_effects.apply_drift(clean.capture.frames[k, 0].astype(np.float32), t.drift_gain[k],
                                          t.drift_offset[k], field)
        ok = (want > 1) & (want < 254)  # away from clipping
        err = np.abs(drifted.capture.frames[k, 0].astype(np.float32) - want)[ok]
        assert err.max() <= 0.5 / 0.85 + 1.0  # one rounding of the clean frame, scaled, plus one of the drifted


def test_markers_are_dark_where_the_truth_says():
    s = random_sensor(6, shape=(90, 120), num_presses=1, effects=["markers"])
    out = render_sensor(s)
    m = out.truth.markers
    assert 0.02 < m.mean() < 0.3
    ref = out.capture.reference[0].astype(float).sum(-1)
    from scipy import ndimage

    ring = ndimage.binary_dilation(m, iterations=3) & ~ndimage.binary_dilation(m, iterations=1)
    assert ref[m].mean() < (1 - s.marker_darkness / 2) * ref[ring].mean()


def test_same_seed_same_frames_and_sizes_portrait():
    a = render_sensor(random_sensor(8, shape=SMALL, num_presses=1))
    b = render_sensor(random_sensor(8, shape=SMALL, num_presses=1))
    np.testing.assert_array_equal(a.capture.frames, b.capture.frames)
    shapes = {random_sensor(seed).shape for seed in range(12)}
    assert any(h > w for h, w in shapes) and any(h < w for h, w in shapes)
    big = render_sensor(random_sensor(9, shape=(640, 480), num_presses=1, effects=["jpeg", "column_stripes"]))
    assert big.capture.frames.shape == (1, 1, 640, 480, 3)


def test_capture_file_round_trip(tmp_path, plain):
    s = random_sensor(10, shape=SMALL, num_presses=2, effects=["markers", "jpeg"])
    out = write_sensor_capture(tmp_path / "v.h5", s, labels=True)
    cap = read_capture(tmp_path / "v.h5")
    np.testing.assert_array_equal(cap.frames, out.capture.frames)
    assert cap.meta["source"] == "virtual-sensor" and cap.meta["ball_radius_mm"] == s.ball_radius_mm
    np.testing.assert_allclose(cap.labels["center_xy"], out.truth.center_xy, atol=1e-4)
    assert cap.truth["markers"].shape == SMALL and cap.truth["contact"].shape == (2,) + SMALL
    one = cap.select([1])  # per-press truth is selected, the marker mask kept whole
    assert one.truth["markers"].shape == SMALL and one.truth["contact"].shape == (1,) + SMALL
    assert VirtualSensor(**cap.meta["virtual_sensor"]).to_dict() == s.to_dict()


def test_image_folder_imports_with_its_reference_and_labels(tmp_path):
    s = random_sensor(12, shape=SMALL, num_presses=4, effects=["jpeg", "read_noise"])
    res = virtual_sensor.write_sensor_images(tmp_path / "imgs", s)
    cap, report = load_images(tmp_path / "imgs", mm_per_px=s.mm_per_px, labels=res["labels"])
    assert report["reference"] == res["reference"]  # found automatically
    assert cap.meta["frame_names"] == res["press_names"]
    sc = res["sensor_capture"]
    np.testing.assert_array_equal(cap.frames, sc.capture.frames)  # the .jpg files hold exactly those frames
    np.testing.assert_allclose(cap.labels["center_xy"], sc.truth.center_xy, atol=1e-3)


def test_bad_sensors_are_refused():
    with pytest.raises(ValueError, match="contact radii"):
        VirtualSensor(ball_radius_mm=1.0, mm_per_px=0.1, contact_radii_px=(12.0,))
    with pytest.raises(ValueError, match="unknown effect"):
        random_sensor(0, effects=["fog"])
    with pytest.raises(ValueError, match="jpeg_quality"):
        VirtualSensor(jpeg_quality=101)



def test_cli_writes_a_capture_and_an_image_folder(tmp_path, capsys):
    import json

    from pipeline.cli import main

    code = main(["sim", "sensor", "--seed", "3", "--shape", "40", "60", "--presses", "2", "--effects", "jpeg,markers",
                 "--out", str(tmp_path / "s.h5"), "--images", str(tmp_path / "imgs"), "--json"])
    assert code == 0
    res = json.loads(capsys.readouterr().out)
    assert res["effects"] == ["markers", "jpeg"] and (tmp_path / "imgs" / res["reference"]).is_file()
    assert read_capture(tmp_path / "s.h5").frames.shape == (2, 1, 40, 60, 3)
    assert main(["sim", "sensor", "--effects", "fog", "--out", str(tmp_path / "x.h5")]) == 2
    assert "unknown effect" in capsys.readouterr().err and not (tmp_path / "x.h5").exists()


def test_rim_smoothing_and_blur_are_what_the_truth_says():
    """Rim smoothing: the truth is the smoothed cap, the sphere's normals wrong near the rim and
    within a degree beyond SPHERE_TRUST_SIGMAS; optical blur: the frame is the blurred clean one."""
    from calibration.truth import SPHERE_TRUST_SIGMAS, rim_error_profile

    s = random_sensor(13, shape=(90, 120), num_presses=1, effects=["rim_smoothing", "optical_blur"],
                      border_fraction=0.0).replace(rim_smoothing_px=2.0, blur_px=2.0, ball_radius_mm=3.0, mm_per_px=0.1, contact_radii_px=(20.0,))
    out = render_sensor(s)
    (x, y), a = out.truth.center_xy[0], out.truth.radius_px[0]
    prof = rim_error_profile(out.truth.normals[0], (y, x), a, s.ball_radius_mm, s.mm_per_px, 1.0, 8)
    assert prof[0] > 5 and np.nanmax(prof[int(SPHERE_TRUST_SIGMAS * 2):]) < 1.0, prof
    sharp = render_sensor(s.replace(blur_px=0.0))
    want = sensor_effects.optical_blur(sharp.capture.frames[0, 0].astype(np.float32), 2.0)
    err = np.abs(out.capture.frames[0, 0].astype(np.float32) - want)[4:-4, 4:-4]
    assert err.max() <= 1.0 and np.abs(out.capture.frames.astype(float) - sharp.capture.frames).max() > 5


def test_moved_markers_are_where_the_press_pushed_them():
    """Under a press the dots move outward (the reference's mask no longer covers them); away from it they stay."""
    s = random_sensor(1, shape=(120, 160), num_presses=2, effects=["markers", "marker_motion"], border_fraction=0.0)
    out = render_sensor(s)
    ref_mask, moved = out.truth.markers, out.truth.press_markers
    assert moved.shape == (2, 120, 160)
    yy, xx = np.mgrid[:120, :160]
    for k in range(2):
        (cx, cy), a = out.truth.center_xy[k], out.truth.radius_px[k]
        near = np.hypot(xx - cx, yy - cy) < 1.5 * a
        far = np.hypot(xx - cx, yy - cy) > 4 * a
        assert (moved[k] & ~ref_mask & near).sum() > 10  # dots left the reference's mask
        assert (moved[k] ^ ref_mask)[far].mean() < 0.05  # a fraction of a pixel there: edge pixels only


def test_soft_shading_puts_the_brightest_change_on_a_rim_crescent():
    s = random_sensor(0, shape=(120, 160), num_presses=1, effects=["soft_shading"], border_fraction=0.0,
                      radius_range=(0.7, 0.8))
    soft = render_sensor(s)
    plain = render_sensor(s.replace(soft_shading=0.0, soft_blur_px=0.0, rim_highlight_dn=0.0))
    def change(out):
        return np.abs(out.capture.frames[0, 0].astype(float) - out.capture.reference[0]).sum(-1)
    d_soft, d_plain = change(soft), change(plain)
    (cx, cy), a = soft.truth.center_xy[0], soft.truth.radius_px[0]
    y, x = np.unravel_index(np.argmax(d_soft), d_soft.shape)
    assert 0.3 * a < np.hypot(x - cx, y - cy) < 1.1 * a  # the peak is off centre, toward the rim
    inside = soft.truth.contact[0]
    assert np.median(d_soft[inside]) < 0.8 * np.median(d_plain[inside])  # the rest of the shading is weaker
