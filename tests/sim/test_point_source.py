"""The closed-form bare-LED field: energy, inverse-square law, cone, ring symmetry."""

import math

import numpy as np
import pytest

from pipeline.base.frames import pixel_to_optical
from sim.point_source import led_intensity_scale, point_source_field, ring_geometry


@pytest.mark.parametrize("m,cone", [(1.0, 60.0), (1.0, 90.0), (3.0, 45.0)])
def test_all_emitted_power_lands_on_an_infinite_plane(m, cone):
    # A plane 5 mm above an LED facing it catches every ray inside a cone < 90 deg.
    z, s, n = 5.0, 0.05, 1201
    reach = z * math.tan(math.radians(min(cone, 85.0)))
    V = point_source_field([[0, 0, 0]], [[0, 0, 1]], (n, n), s, z, m=m, cone_half_angle_deg=cone, dtype=np.float64)
    flux = V[0, ..., 2].sum() * s * s
    # the grid covers +-30 mm; for the 90-degree cone the far tail misses it: compute that part
    half = (n - 1) / 2 * s
    if cone >= 90.0:
        # fraction of a cos^m emitter beyond polar angle atan(half/z) ~ cos^(m+1)(theta_edge)
        expected = 1.0 - math.cos(math.atan(half * 1.1 / z)) ** (m + 1)
        assert flux == pytest.approx(expected, abs=0.03)
    else:
        assert reach < half
        assert flux == pytest.approx(1.0, abs=2e-3)


def test_inverse_square_and_lambert_cosine_on_axis_and_off_axis():
    V = point_source_field([[0, 0, 0]], [[0, 0, 1]], (1, 3), 2.0, 4.0, cone_half_angle_deg=90.0, dtype=np.float64)
    i0 = led_intensity_scale(1.0, 90.0)
    on_axis = V[0, 0, 1]
    assert on_axis[2] == pytest.approx(i0 / 16.0) and on_axis[0] == 0 and on_axis[1] == 0
    off = V[0, 0, 2]  # at x = +2 mm: the LED lies toward -x, so V points -x
    d2 = 4.0 + 16.0
    cos_t = 4.0 / math.sqrt(d2)
    assert np.linalg.norm(off) == pytest.approx(i0 * cos_t / d2)
    assert off[0] < 0 and off[2] > 0


def test_nothing_outside_the_cone():
    V = point_source_field([[0, 0, 0]], [[0, 0, 1]], (1, 41), 1.0, 5.0, cone_half_angle_deg=30.0)
    x, _ = pixel_to_optical(0, np.arange(41), (1, 41), 1.0)
    outside = np.abs(x) > 5.0 * math.tan(math.radians(30.0)) + 1e-9
    assert np.all(V[0, 0, outside] == 0) and np.all(V[0, 0, ~outside, 2] > 0)


def test_ring_image_has_24_fold_symmetry():
    pos, axes = ring_geometry(24, 40.0)
    n = 61
    V = point_source_field(pos, axes, (n, n), 1.5, 30.0, dtype=np.float64)
    E = V[..., 2].sum(axis=0)  # flat-gel irradiance of the whole ring
    np.testing.assert_allclose(E, E.T, rtol=1e-10)  # mirror about the diagonal
    np.testing.assert_allclose(E, E[::-1, :], rtol=1e-10)
    # LED k's image is LED 0's image rotated by 15 k degrees: check LED 6 (90 deg) exactly
    np.testing.assert_allclose(np.rot90(V[0, ..., 2], k=-1), V[6, ..., 2], rtol=1e-9, atol=1e-15)


def test_depth_dependent_field_moves_the_surface_toward_the_leds():
    V0 = point_source_field([[0, 0, 0]], [[0, 0, 1]], (1, 1), 1.0, 10.0)
    V1 = point_source_field([[0, 0, 0]], [[0, 0, 1]], (1, 1), 1.0, 10.0, gel_height=np.full((1, 1), 1.0))
    assert V1[0, 0, 0, 2] / V0[0, 0, 0, 2] == pytest.approx(100 / 81, rel=1e-5)


def test_shape_errors_print_what_was_received():
    with pytest.raises(ValueError, match=r"\(2, 3\) and axes \(1, 3\)"):
        point_source_field(np.zeros((2, 3)), np.zeros((1, 3)), (2, 2), 1.0, 1.0)
