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


def _four_presses(radius_px: float, noise_dn: float):
    """``(frames, reference, circles)``: four rendered presses of one radius, linear, each with its
    true circle accepted."""
    from calibration.detect import Circle
    from calibration.synthetic import synthetic_sphere_capture

    centres = [(30.0, 30.0), (30.0, 90.0), (60.0, 40.0), (60.0, 100.0)]
    cap, _ = synthetic_sphere_capture((90, 130), centers_rc=centres, radii_px=[radius_px] * 4, ball_radius_mm=1.5,
                                      num_leds=3, noise_dn=noise_dn, peak_dn=120.0)
    f, r = cap.linear()
    circles = [Circle(center_xy=(c, rr), radius_px=radius_px, contact_radius_px=radius_px, quality=1.0,
                      accepted=True, reason="ok") for rr, c in centres]
    return f, r, circles


def test_a_faint_press_is_judged_on_the_change_above_its_noise():
    """Small, faint presses at a high noise: the true circles explain nearly all of the change
    above the noise, so none is refused for a share of the raw change that noise alone caps."""
    f, r, circles = _four_presses(8.0, 3.0)
    _, report = refit_by_shading(f, r, circles, 15.0)
    assert min(report["explained"]) > 0.9, report["explained"]


def test_an_accepted_circle_with_no_contact_under_it_is_refused():
    """An edge circle drawn on flat gel (noise, a ring of moved dots), while the press is
    elsewhere: the shading the other presses show explains nothing around it, so it is refused
    and says why; the presses whose circles are right stay accepted where they are."""
    from dataclasses import replace

    frames, r, circles = _four_presses(9.0, 2.0)
    f = frames.copy()
    f[3] = r  # the fourth press shows no contact: its circle lies on flat gel
    out, report = refit_by_shading(f, r, circles, 15.0)
    assert [c.accepted for c in out] == [True, True, True, False], [c.reason for c in out]
    assert out[3].reason.startswith("no contact at the circle") and report["explained"][3] < 0.05
    assert all(o.center_xy == c.center_xy for o, c in zip(out[:3], circles[:3]))
    # With the contact where its circle is, nothing is refused.
    kept, _ = refit_by_shading(frames, r, [replace(c) for c in circles], 15.0)
    assert all(c.accepted for c in kept)


def test_an_edge_circle_the_detector_doubted_is_accepted_where_the_shading_confirms_it():
    """A right circle the edge detector refused as no clear circle (its rays disagreed: a ring
    of moved dots) is accepted where it is, saying so; one refused for its size stays refused."""
    from dataclasses import replace

    frames, r, circles = _four_presses(9.0, 2.0)
    doubted = replace(circles[3], accepted=False, reason="no clear circle: 35% of rays agree (< 50%)")
    out, report = refit_by_shading(frames, r, circles[:3] + [doubted], 15.0)
    assert out[3].accepted and out[3].reason.startswith("confirmed by its shading"), out[3].reason
    assert np.hypot(*np.subtract(out[3].center_xy, circles[3].center_xy)) < 0.5
    assert report["explained"][3] >= 0.5
    sized = replace(circles[3], accepted=False, reason="far smaller than the ball: r 9 px")
    out, _ = refit_by_shading(frames, r, circles[:3] + [sized], 15.0)
    assert not out[3].accepted


def test_a_press_refused_for_disagreeing_rays_is_rescued_by_a_weaker_shading_than_others_need():
    """A small press the edge detector refused as no clear circle, with a change beside it that no
    cap explains (two moved dots): its right circle explains 45 % of the change, under
    ``min_explained`` but over ``min_rescue``, and is taken. Asked for half, with the dots
    darker (13 % explained), or refused for its size instead, the edge detector's refusal stands."""
    from dataclasses import replace

    from calibration.shading_fit import ShadingOptions

    frames, r, circles = _four_presses(9.0, 2.0)
    rows, cols = np.mgrid[0:frames.shape[2], 0:frames.shape[3]]
    dots = sum(np.exp(-((rows - y) ** 2 + (cols - x) ** 2) / (2 * 2.5 ** 2)) for x, y in ((117, 60), (100, 44)))
    doubted = replace(circles[3], accepted=False, reason="no clear circle: 35% of rays agree (< 50%)")
    sized = replace(circles[3], accepted=False, reason="far smaller than the ball: r 1.2 px", radius_px=1.2)
    for gain, refused, options, taken in ((80.0, doubted, None, True), (80.0, doubted, ShadingOptions(min_rescue=0.5), False),
                                          (200.0, doubted, None, False), (80.0, sized, None, False)):
        f = frames.copy()
        f[3] += gain * dots[None, :, :, None]
        out, report = refit_by_shading(f, r, circles[:3] + [refused], 15.0, options=options)
        assert out[3].accepted is taken, (gain, refused.reason, report["explained"][3], out[3].reason)
        assert (0.25 < report["explained"][3] < 0.5) is (gain == 80.0), report["explained"][3]
        if taken:
            assert np.hypot(*np.subtract(out[3].center_xy, circles[3].center_xy)) < 0.5
            assert out[3].reason.startswith("confirmed by its shading (shading explains 45%"), out[3].reason
        else:
            assert out[3].reason.startswith(refused.reason)


def test_an_accepted_edge_circle_shifted_inside_the_contact_is_moved_by_the_shading():
    """An accepted edge circle 20 % small and 3 px off its press (a soft gel's edges circling inside a
    broad contact) is replaced by the shading's circle, within 1 px of the truth; the same circle is
    kept where the shading's cap is as wide as the ball (the gel changing around a contact, not the
    contact: :func:`calibration.shading_fit._edge_failed`'s ``largest_contact``)."""
    from dataclasses import replace

    from calibration.detect import Circle
    from calibration.shading_fit import ShadingOptions, _edge_failed

    frames, r, circles = _four_presses(10.0, 1.0)
    x, y = circles[3].center_xy
    off = replace(circles[3], center_xy=(x + 3.0, y), radius_px=8.0, contact_radius_px=8.0)
    out, _ = refit_by_shading(frames, r, circles[:3] + [off], 15.0)
    assert out[3].accepted and "by its shading" in out[3].reason, out[3].reason
    assert np.hypot(*np.subtract(out[3].center_xy, circles[3].center_xy)) < 1.0, out[3].center_xy
    edge = Circle((0.0, 0.0), 8.0, 8.0, 1.0, True, "ok")
    opt = ShadingOptions()
    assert _edge_failed(edge, (0.0, 0.0, 8.0), (3.0, 0.0, 10.0), opt, largest_contact=14.25)
    assert not _edge_failed(edge, (0.0, 0.0, 8.0), (3.0, 0.0, 14.5), opt, largest_contact=14.25)
    assert not _edge_failed(edge, (0.0, 0.0, 8.0), (0.5, 0.0, 10.0), opt, largest_contact=14.25)
