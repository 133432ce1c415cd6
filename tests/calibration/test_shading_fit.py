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


def test_an_accepted_circle_with_no_contact_under_it_is_refused():
    """An edge circle drawn on flat gel (noise, a ring of moved dots), while the press is
    elsewhere: the shading the other presses show explains nothing around it, so it is refused
    and says why; the presses whose circles are right stay accepted where they are."""
    from dataclasses import replace

    from calibration.detect import Circle
    from calibration.synthetic import synthetic_sphere_capture

    centres = [(30.0, 30.0), (30.0, 90.0), (60.0, 40.0), (60.0, 100.0)]
    cap, truth = synthetic_sphere_capture((90, 130), centers_rc=centres, radii_px=[9.0] * 4, ball_radius_mm=1.5,
                                          num_leds=3, noise_dn=2.0, peak_dn=120.0)
    f, r = cap.linear()
    circles = [Circle(center_xy=(c, rr), radius_px=9.0, contact_radius_px=9.0, quality=1.0, accepted=True, reason="ok")
               for rr, c in centres]
    f = f.copy()
    f[3] = r  # the fourth press shows no contact: its circle lies on flat gel
    out, report = refit_by_shading(f, r, circles, 15.0)
    assert [c.accepted for c in out] == [True, True, True, False], [c.reason for c in out]
    assert out[3].reason.startswith("no contact at the circle") and report["explained"][3] < 0.05
    assert all(o.center_xy == c.center_xy for o, c in zip(out[:3], circles[:3]))
    # With the contact where its circle is, nothing is refused.
    kept, _ = refit_by_shading(cap.linear()[0], r, [replace(c) for c in circles], 15.0)
    assert all(c.accepted for c in kept)
