"""Pin the sign of every axis of the coordinate conventions (pipeline/base/frames.py)."""

import numpy as np
import pytest

from pipeline.base import frames


def test_pixel_axes_in_both_frames():
    shape = (5, 7)
    cy, cx = frames.pixel_centers(shape)
    assert (cy, cx) == (2.0, 3.0)
    # centre pixel on the axis
    assert [float(v) for v in frames.pixel_to_optical(2, 3, shape, 0.1)] == [0.0, 0.0]
    # one column right: +x in both frames
    xo, yo = frames.pixel_to_optical(2, 4, shape, 0.1)
    xr, yr = frames.pixel_to_recon(2, 4, shape, 0.1)
    assert xo == pytest.approx(0.1) and xr == pytest.approx(0.1) and yo == 0 and yr == 0
    # one row down: +y optical, -y reconstruction
    xo, yo = frames.pixel_to_optical(3, 3, shape, 0.1)
    xr, yr = frames.pixel_to_recon(3, 3, shape, 0.1)
    assert yo == pytest.approx(0.1) and yr == pytest.approx(-0.1)


def test_frame_rotation_is_proper_and_involutive():
    R = np.stack([frames.optical_to_recon(e) for e in np.eye(3)], axis=1)
    assert np.linalg.det(R) == pytest.approx(1.0)
    v = np.random.default_rng(0).standard_normal((10, 3))
    np.testing.assert_allclose(frames.recon_to_optical(frames.optical_to_recon(v)), v)
    # toward the camera: optical -z is reconstruction +z
    np.testing.assert_allclose(frames.optical_to_recon([0, 0, -1.0]), [0, 0, 1.0])


def test_optical_to_recon_works_on_torch():
    torch = pytest.importorskip("torch")
    v = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    assert frames.optical_to_recon(v).tolist() == [[1.0, -2.0, -3.0]]


def test_ball_pressed_in_gives_a_positive_bump_whose_normals_point_outward():
    """A sphere cap rising toward the camera: normals tilt away from the cap's centre."""
    shape, s = (41, 41), 0.05
    rows, cols = np.mgrid[0:41, 0:41]
    x, y = frames.pixel_to_recon(rows, cols, shape, s)
    R, depth = 2.0, 0.5
    z0 = depth - R  # sphere centre below the gel surface plane
    r2 = x**2 + y**2
    h = np.where(r2 < R**2, np.sqrt(np.maximum(R**2 - r2, 0)) + z0, 0.0)
    h = np.maximum(h, 0.0)
    assert h[20, 20] == pytest.approx(depth)  # positive toward the camera
    n = frames.normals_from_height(h, s)
    # right of centre (+x): normal leans +x; above centre in the image (row smaller, +y): leans +y
    assert n[20, 24, 0] > 0.05 and abs(n[20, 24, 1]) < 1e-9
    assert n[16, 20, 1] > 0.05 and abs(n[16, 20, 0]) < 1e-9
    # compare with the exact sphere normal (x, y, z - z0) / R at an interior pixel
    exact = np.array([x[20, 23], y[20, 23], h[20, 23] - z0]) / R
    np.testing.assert_allclose(n[20, 23], exact, atol=2e-3)
    # and the flat gel is (0, 0, 1)
    np.testing.assert_allclose(n[0, 0], [0, 0, 1])


def test_gradients_and_normals_round_trip(dtype):
    rng = np.random.default_rng(1)
    p, q = rng.standard_normal(50), rng.standard_normal(50)
    n = frames.gradients_to_normals(p, q)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0)
    p2, q2 = frames.normals_to_gradients(n.astype(dtype.np), dtype=dtype.np)
    assert p2.dtype == dtype.np and q2.dtype == dtype.np
    np.testing.assert_allclose(p2, p, rtol=dtype.tol(1e-12, 1e-5))
    np.testing.assert_allclose(q2, q, rtol=dtype.tol(1e-12, 1e-5))
    # grazing normals give finite gradients
    assert np.all(np.isfinite(frames.normals_to_gradients(np.array([1.0, 0, 0], dtype.np), dtype=dtype.np)))


def test_pixel_steps_follow_the_image_axes(dtype):
    """A surface rising along +x rises toward larger columns; rising along +y, toward smaller rows."""
    dcol, drow = frames.gradients_to_pixel_steps(np.array(0.5, dtype.np), np.array(0.25, dtype.np), 0.1)
    assert dcol.dtype == dtype.np and drow.dtype == dtype.np
    assert dcol == pytest.approx(0.05, rel=dtype.tol(1e-12, 1e-6)) and drow == pytest.approx(-0.025, rel=dtype.tol(1e-12, 1e-6))
    p, q = frames.pixel_steps_to_gradients(dcol, drow, 0.1)
    assert p == pytest.approx(0.5, rel=dtype.tol(1e-12, 1e-6)) and q == pytest.approx(0.25, rel=dtype.tol(1e-12, 1e-6))
    # The same convention as normals_from_height: a ramp along the columns has n_x < 0.
    h = np.tile(np.arange(5.0), (4, 1)) * dcol
    n = frames.normals_from_height(h, 0.1)
    assert n[1, 2, 0] < 0 and abs(n[1, 2, 1]) < 1e-12
