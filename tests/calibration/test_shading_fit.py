"""The shading refit's judge: what share of a press's colour change above the camera's noise a circle explains."""

import numpy as np
import pytest

from calibration.shading_fit import noise_variance, refit_by_shading


@pytest.mark.parametrize("sigma", [0.5, 2.0, 6.0])
def test_noise_variance_of_white_noise_despite_a_contact(sigma):
    rng = np.random.default_rng(0)
    img = rng.normal(0.0, sigma, (80, 100, 3))
    rows, cols = np.mgrid[0:80, 0:100]
    img[np.hypot(rows - 40, cols - 50) < 12] += 40.0  # a contact: a small part of the image
    var = noise_variance(img, np.ones((80, 100), bool))
    np.testing.assert_allclose(var, sigma ** 2, rtol=0.15)


def test_a_faint_press_is_judged_on_the_change_above_its_noise():
    """Small, faint presses at a high noise: the true circles explain nearly all of the change
    above the noise, so none is refused for a share of the raw change that noise alone caps."""
    from calibration.detect import Circle
    from calibration.synthetic import synthetic_sphere_capture

    centres = [(30.0, 30.0), (30.0, 90.0), (60.0, 40.0), (60.0, 100.0)]
    cap, truth = synthetic_sphere_capture((90, 130), centers_rc=centres, radii_px=[8.0] * 4, ball_radius_mm=1.5,
                                          num_leds=3, noise_dn=3.0, peak_dn=120.0)
    f, r = cap.linear()
    circles = [Circle(center_xy=(c, rr), radius_px=8.0, contact_radius_px=8.0, quality=1.0, accepted=True, reason="ok")
               for rr, c in centres]
    _, report = refit_by_shading(f, r, circles, 15.0)
    assert min(report["explained"]) > 0.9, report["explained"]
