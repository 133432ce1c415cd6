"""Contact geometry: signs pinned to pipeline.base.frames, analytic gradients against derivatives of the heights."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from pipeline.base.errors import UserError
from pipeline.base.frames import normals_from_height, pixel_to_recon
from sim.geometry import (
    HeightField,
    add_texture,
    combine,
    cone,
    cylinder,
    flat,
    flat_punch,
    height_from_file,
    smooth,
    sphere,
    wedge,
)

SHAPE = (40, 60)
PX = 0.1


def _numeric_gradients(make, center, delta=1e-5):
    """dh/dx, dh/dy by moving the shape: h(x + d; c) = h(x; c - d). Exact up to O(delta^2).

    Also returns the pixels whose contact status is the same in all four shifted maps: only
    there is the surface smooth across the stencil (a pixel exactly on the contact rim sits on
    a kink, where the derivative does not exist).
    """
    cx, cy = center
    fx1, fx0 = make((cx - delta, cy)), make((cx + delta, cy))
    fy1, fy0 = make((cx, cy - delta)), make((cx, cy + delta))
    same = (fx1.contact == fx0.contact) & (fy1.contact == fy0.contact) & (fx1.contact == fy1.contact)
    return (fx1.height - fx0.height) / (2 * delta), (fy1.height - fy0.height) / (2 * delta), same


def _check_gradients(make, center, atol=1e-4):
    f = make(center)
    p, q, same_piece = _numeric_gradients(make, center)
    # Compare where all shifted maps agree on the piece of surface (away from kinks/steps).
    smooth_px = same_piece & (np.abs(p - f.p) < 1e3) & (np.abs(q - f.q) < 1e3)
    ok = np.isclose(p, f.p, atol=atol, rtol=1e-4) & np.isclose(q, f.q, atol=atol, rtol=1e-4)
    bad = smooth_px & ~ok
    # only pixels within delta of a kink may disagree: there are almost none
    assert bad.sum() <= 0.002 * bad.size, (bad.sum(), np.abs(p - f.p)[bad][:5])
    return f


def test_sphere_sign_convention_bump_toward_camera_and_normals_outward():
    f = sphere(SHAPE, PX, radius=2.0, depth=0.5)
    cy, cx = (SHAPE[0] - 1) / 2, (SHAPE[1] - 1) / 2
    assert f.height.max() == pytest.approx(0.5, abs=5e-3)  # positive bump toward the camera
    assert f.height.min() == 0.0
    n = f.normals
    r, c = int(cy), int(cx) + 5  # right of the peak: larger column = +x
    assert n[r, c, 0] > 0.1 and n[r, c, 2] > 0
    r, c = int(cy) - 5, int(cx)  # above the peak: smaller row = +y
    assert n[r, c, 1] > 0.1
    # agrees with the shared finite-difference normals of pipeline.base.frames in the interior
    fd = normals_from_height(f.height, PX)
    inner = sphere(SHAPE, PX, radius=2.0, depth=0.4).contact  # well inside the rim
    assert np.max(np.abs(fd[inner] - n[inner])) < 0.02


def test_sphere_normals_are_the_sphere_normals():
    R, d = 2.0, 0.6
    f = sphere(SHAPE, PX, R, d, center=(0.3, -0.2))
    rows, cols = np.nonzero(f.contact)
    x, y = pixel_to_recon(rows, cols, SHAPE, PX)
    # centre of the ball in the reconstruction frame (z relative to the gel plane)
    c = np.array([0.3, -0.2, d - R])
    pts = np.stack([x, y, f.height[rows, cols]], -1)
    expected = (pts - c) / R
    np.testing.assert_allclose(f.normals[rows, cols], expected, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(pts - c, axis=-1), R, atol=1e-12)
    # contact radius a = sqrt(2Rd - d^2)
    a = math.sqrt(2 * R * d - d * d)
    assert f.contact.sum() * PX * PX == pytest.approx(math.pi * a * a, rel=0.03)


@pytest.mark.parametrize("make", [
    lambda c: sphere(SHAPE, PX, 1.5, 0.4, center=c),
    lambda c: cylinder(SHAPE, PX, 1.0, 0.3, center=c, angle_deg=30.0),
    lambda c: cylinder(SHAPE, PX, 1.0, 0.3, center=c, angle_deg=-70.0, length=2.0),
    lambda c: flat_punch(SHAPE, PX, 1.0, 0.3, center=c, edge_radius=0.5),
    lambda c: flat_punch(SHAPE, PX, 1.0, 0.3, center=c, edge_radius=0.2),
    lambda c: cone(SHAPE, PX, 60.0, 0.8, center=c),
    lambda c: wedge(SHAPE, PX, 50.0, 0.4, center=c, angle_deg=20.0),
], ids=["sphere", "cylinder", "cylinder-finite", "punch-round", "punch-step", "cone", "wedge"])
def test_analytic_gradients_match_derivatives_of_the_heights(make):
    f = _check_gradients(make, (0.13, -0.21))
    assert f.contact.any() and np.all(f.height[~f.contact] == 0.0)
    assert np.all(np.isfinite(f.normals)) and np.allclose(np.linalg.norm(f.normals, axis=-1), 1.0)


@settings(max_examples=25, deadline=None)
@given(R=st.floats(0.5, 5.0), frac=st.floats(0.05, 0.95), cx=st.floats(-1.5, 1.5), cy=st.floats(-1.0, 1.0))
@example(R=0.75, frac=1 / 3, cx=0.0, cy=0.05)  # pixels exactly on the contact rim (a kink)
def test_sphere_gradients_property(R, frac, cx, cy):
    d = frac * R
    _check_gradients(lambda c: sphere((30, 40), 0.1, R, d, center=c), (cx, cy), atol=1e-3)


def test_flat_punch_face_and_step():
    f = flat_punch(SHAPE, PX, 1.0, 0.3, edge_radius=0.1)
    assert np.all(f.normals[f.height == 0.3] == [0.0, 0.0, 1.0])
    # edge radius < depth leaves a vertical wall: heights jump from >= depth - e to 0
    outer = f.height[(f.height > 0) & (f.height < 0.3)]
    assert outer.min() >= 0.2 - 1e-12
    sharp = flat_punch(SHAPE, PX, 1.0, 0.3, edge_radius=0.0)
    assert set(np.unique(sharp.height)) == {0.0, 0.3} and np.all(sharp.p == 0)


def test_cone_and_wedge_slopes():
    f = cone(SHAPE, PX, 30.0, 1.0)
    slope = np.hypot(f.p, f.q)[f.contact]
    cot = 1 / math.tan(math.radians(30))
    assert np.all((np.abs(slope - cot) < 1e-9) | (slope == 0))
    w = wedge(SHAPE, PX, 45.0, 0.5, angle_deg=90.0)  # ridge along y: slopes along x only
    assert np.allclose(w.q, 0.0) and np.allclose(np.abs(w.p[w.contact & (w.p != 0)]), 1.0)


def test_combine_takes_the_highest_indenter():
    a = sphere(SHAPE, PX, 1.0, 0.3, center=(-1.0, 0.0))
    b = cone(SHAPE, PX, 60.0, 0.5, center=(1.2, 0.3))
    c = combine([a, b])
    np.testing.assert_array_equal(c.height, np.maximum(a.height, b.height))
    on_b = b.height > a.height
    np.testing.assert_array_equal(c.p[on_b], b.p[on_b])
    np.testing.assert_array_equal(c.contact, a.contact | b.contact)
    with pytest.raises(ValueError, match="differ"):
        combine([a, sphere((10, 10), PX, 1.0, 0.3)])


def test_smoothing_conserves_volume_and_gradients_are_its_derivatives():
    f = flat_punch((60, 60), 0.05, 0.6, 0.2, edge_radius=0.0)
    s = smooth(f, 0.1)
    assert s.height.sum() == pytest.approx(f.height.sum(), rel=1e-9)  # blur conserves volume
    assert s.height.max() < f.height.max()
    fd = normals_from_height(s.height, 0.05)
    np.testing.assert_allclose(s.normals, fd, atol=0.03)
    assert smooth(f, 0.0) is f


def test_texture_gradients_and_confinement():
    base = sphere(SHAPE, PX, 2.0, 0.5)
    for kind in ("grating", "random"):
        def make(c, kind=kind):
            return add_texture(sphere(SHAPE, PX, 2.0, 0.5), 0.01, 0.4, 30.0, kind=kind, seed=3)

        t = make((0.0, 0.0))
        assert np.all(t.height[~base.contact] == 0)
        assert np.abs(t.height - base.height).max() <= 0.01 + 1e-12
        # texture gradient is the exact derivative of the texture term (checked on a finer grid)
        fd = normals_from_height(t.height, PX)
        inner = sphere(SHAPE, PX, 2.0, 0.3).contact
        assert np.abs(fd[inner] - t.normals[inner]).max() < 0.05
    with pytest.raises(ValueError, match="kind"):
        add_texture(base, 0.01, 0.4, kind="noise")


def test_height_from_npy_and_png(tmp_path):
    import cv2

    f = sphere((30, 40), 0.1, 2.0, 0.5)
    np.save(tmp_path / "h.npy", f.height)
    g = height_from_file(tmp_path / "h.npy", 0.1)
    np.testing.assert_array_equal(g.height, f.height)
    np.testing.assert_allclose(g.normals, normals_from_height(f.height, 0.1), atol=1e-12)
    png = np.round(f.height / 1e-4).astype(np.uint16)  # 0.1 um per level
    cv2.imwrite(str(tmp_path / "h.png"), png)
    g = height_from_file(tmp_path / "h.png", 0.1, mm_per_unit=1e-4)
    assert np.abs(g.height - f.height).max() <= 0.5e-4 + 1e-12
    g2 = height_from_file(tmp_path / "h.png", 0.1, mm_per_unit=1e-4, shape=(15, 20))
    assert g2.shape == (15, 20) and g2.mm_per_px == pytest.approx(0.2)


def test_height_from_file_errors_name_the_file(tmp_path):
    with pytest.raises(UserError, match="nope.npy"):
        height_from_file(tmp_path / "nope.npy", 0.1)
    np.save(tmp_path / "cube.npy", np.zeros((2, 3, 4)))
    with pytest.raises(UserError, match=r"cube.npy.*\(2, 3, 4\)"):
        height_from_file(tmp_path / "cube.npy", 0.1)
    (tmp_path / "h.txt").write_text("1 2")
    with pytest.raises(UserError, match="h.txt.*npy or .png"):
        height_from_file(tmp_path / "h.txt", 0.1)


def test_bad_parameters_raise_with_the_value():
    with pytest.raises(ValueError, match="depth must be < radius"):
        sphere(SHAPE, PX, 1.0, 1.0)
    with pytest.raises(ValueError, match="radius"):
        sphere(SHAPE, PX, -1.0, 0.1)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        HeightField(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3, bool), 0.1)
    assert flat((3, 4), 0.1).normals[..., 2].min() == 1.0
