"""Sphere-cap truth and contact detection on synthetic presses with known circles."""

import numpy as np
import pytest

from calibration.detect import DetectOptions, detect_press
from calibration.synthetic import synthetic_sphere_capture
from calibration.truth import sphere_cap
from pipeline.base.frames import normals_from_height


def test_sphere_cap_matches_its_own_height_map():
    # The analytic normals must be the normals of the analytic height map (pipeline.base.frames
    # conventions), which pins every sign without restating them here.
    cap = sphere_cap((41, 41), (20.0, 20.0), 12.0, 2.0, 0.1)
    num = normals_from_height(cap.height, 0.1)
    inner = np.hypot(*np.mgrid[-20:21, -20:21]) < 10
    err = np.degrees(np.arccos(np.clip((num * cap.normals).sum(-1), -1, 1)))[inner]
    assert err.max() < 1.0
    assert cap.height.max() == pytest.approx(2.0 - np.sqrt(4.0 - 1.2 ** 2), abs=1e-9)
    assert (cap.height[~cap.contact] == 0).all() and (cap.normals[~cap.contact] == [0, 0, 1]).all()


def test_sphere_cap_rejects_contact_larger_than_ball():
    with pytest.raises(ValueError, match="ball radius"):
        sphere_cap((10, 10), (5, 5), 25.0, 2.0, 0.1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_detect_known_positions(seed):
    cap, tr = synthetic_sphere_capture((60, 80), 4, ball_radius_mm=1.5, num_leds=6, seed=seed)
    f, r = cap.linear()
    for k in range(4):
        c = detect_press(f[k], r, 15.0)
        assert c.accepted, c.reason
        assert np.hypot(c.center_xy[0] - tr.centers_rc[k, 1], c.center_xy[1] - tr.centers_rc[k, 0]) < 0.5
        assert abs(c.radius_px - tr.radii_px[k]) < 1.0


def test_detect_keeps_a_press_half_inside_and_rejects_one_mostly_over_the_border():
    """A half circle pins the circle: 65 % of the rim inside is found within 0.3 px and noted; with its
    centre on the image edge (under half inside, ``DetectOptions.min_rim_inside``) it is refused, saying so."""
    cap, _ = synthetic_sphere_capture((60, 80), centers_rc=[(30.0, 5.0)], radii_px=[10.0], ball_radius_mm=1.5)
    f, r = cap.linear()
    c = detect_press(f[0], r, 15.0)
    assert c.accepted and "of its rim inside the image" in c.reason, c.reason
    assert abs(c.center_xy[0] - 5.0) < 0.3 and abs(c.center_xy[1] - 30.0) < 0.3, c.center_xy
    cap, _ = synthetic_sphere_capture((60, 80), centers_rc=[(30.0, 0.0)], radii_px=[10.0], ball_radius_mm=1.5)
    f, r = cap.linear()
    c = detect_press(f[0], r, 15.0)
    assert not c.accepted and "touches the border" in c.reason and "(< 50%" in c.reason, c.reason


def test_detect_rejects_faint_press():
    # A press with hardly any contact: its difference is lost in the noise.
    cap, _ = synthetic_sphere_capture((60, 80), centers_rc=[(30.0, 40.0)], radii_px=[0.6], ball_radius_mm=1.5)
    f, r = cap.linear()
    c = detect_press(f[0], r, 15.0)
    assert not c.accepted and "faint" in c.reason


def test_detect_no_press_is_not_accepted():
    cap, _ = synthetic_sphere_capture((60, 80), centers_rc=[(30.0, 40.0)], radii_px=[8.0], ball_radius_mm=1.5)
    f, r = cap.linear()
    c = detect_press(r + np.random.default_rng(0).normal(0, 1, r.shape), r, 15.0)
    assert not c.accepted


def test_detect_press_as_large_as_ball_is_clamped():
    cap, tr = synthetic_sphere_capture((70, 90), centers_rc=[(35.0, 45.0)], radii_px=[14.9], ball_radius_mm=1.5)
    f, r = cap.linear()
    c = detect_press(f[0], r, 15.0, DetectOptions(clamp_fraction=0.9))
    assert c.accepted, c.reason
    assert abs(c.radius_px - 14.9) < 1.0
    assert c.contact_radius_px == pytest.approx(0.9 * 15.0) and "clamped" in c.reason
