"""Image formation: flat gel = illumination image, sphere = per-pixel formula, precisions agree."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from pipeline.base.modes import mode_brightness, mode_drive
from sim.geometry import sphere
from sim.lambertian import shade
from sim.point_source import point_source_field, ring_geometry
from sim.render import Renderer, RenderSettings, auto_exposure, bare_ring_illumination, render_images

SHAPE = (30, 40)
PX = 0.4


@pytest.fixture(scope="module")
def model():
    return bare_ring_illumination(SHAPE, PX)


def _eq15_flat(V, drive, brightness, exposure, gains, albedo):
    """Paper eq. 15 on the flat gel: c_j = mu sum_i sigma_i I_i c_ij, with I_i = rho/pi V_i,z."""
    H, W = V.shape[1:3]
    out = np.zeros((len(drive), H, W, 3))
    for p in range(len(drive)):
        for i in range(V.shape[0]):
            I_i = albedo / math.pi * V[i, :, :, 2].astype(np.float64)
            for j in range(3):
                out[p, :, :, j] += exposure * brightness[p] * gains[i] * drive[p, i, j] * I_i
    return out


@pytest.mark.parametrize("mode", ["point", "monochromatic", "trichromatic", "multicolour"])
def test_flat_gel_reproduces_the_illumination_image(model, device, mode):
    drive, bright = mode_drive(mode), mode_brightness(mode)
    gains = np.linspace(0.5, 1.5, 24)
    mu = 1e5
    expected = _eq15_flat(model.V, drive, bright, mu, gains, 0.8)
    s = RenderSettings(exposure=mu, gains=gains)
    got64 = render_images(model, None, drive, bright, albedo=0.8, settings=s, device=device, dtype=torch.float64)
    np.testing.assert_allclose(got64, expected, rtol=1e-12, atol=1e-12 * expected.max())
    got32 = render_images(model, None, drive, bright, albedo=0.8, settings=s, device=device)
    assert got32.dtype == np.float32
    np.testing.assert_allclose(got32, expected, rtol=2e-6, atol=2e-6 * expected.max())


def test_sphere_matches_direct_per_pixel_formula(model):
    """Evaluate I_pj = mu sum_i sigma_i W rho/pi max(0, n . V_i) pixel by pixel in plain Python."""
    surf = sphere(SHAPE, PX, radius=3.0, depth=1.2, center=(0.8, -0.4))
    drive, bright = mode_drive("multicolour"), mode_brightness("multicolour")
    drive = np.concatenate([drive, mode_drive("monochromatic")])
    bright = np.concatenate([bright, mode_brightness("monochromatic")])
    gains = np.linspace(0.7, 1.2, 24)
    albedo = np.random.default_rng(1).uniform(0.3, 1.0, SHAPE + (3,))
    s = RenderSettings(exposure=2e5, gains=gains)
    img = render_images(model, surf, drive, bright, albedo=albedo, settings=s, dtype=torch.float64)
    # Reference normals straight from the sphere, not from the HeightField.
    rng = np.random.default_rng(0)
    pix = [tuple(p) for p in np.argwhere(surf.contact)[rng.choice(surf.contact.sum(), 40, replace=False)]]
    pix += [(0, 0), (29, 39), (15, 20)]
    from pipeline.base.frames import pixel_to_recon

    for r, c in pix:
        x, y = (float(v) for v in pixel_to_recon(r, c, SHAPE, PX))
        dx, dy = x - 0.8, y + 0.4
        rr = dx * dx + dy * dy
        n = (dx / 3.0, dy / 3.0, math.sqrt(9.0 - rr) / 3.0) if surf.contact[r, c] else (0.0, 0.0, 1.0)
        for p in range(len(drive)):
            for j in range(3):
                total = 0.0
                for i in range(24):
                    v = model.V[i, r, c].astype(np.float64)
                    ndotv = n[0] * v[0] + n[1] * v[1] + n[2] * v[2]
                    total += gains[i] * drive[p, i, j] * max(0.0, ndotv)
                want = 2e5 * bright[p] * albedo[r, c, j] / math.pi * total
                assert img[p, r, c, j] == pytest.approx(want, rel=1e-9, abs=1e-12)
    # and the shared formula agrees on the whole image
    ref = shade(model.V, surf.normals, albedo, drive, bright, 2e5, gains)
    np.testing.assert_allclose(img, ref, rtol=1e-10, atol=1e-10 * ref.max())
    # the bump changes the image (it is not the flat gel)
    flat_img = render_images(model, None, drive, bright, albedo=albedo, settings=s, dtype=torch.float64)
    assert np.abs(img - flat_img)[:, surf.contact].max() > 0.05 * flat_img.max()


def test_attached_shadows_off_is_the_linear_model(model):
    surf = sphere(SHAPE, PX, radius=1.5, depth=1.4)  # steep rim: some n . V_i < 0
    drive = mode_drive("point")
    on = render_images(model, surf, drive, settings=RenderSettings(exposure=1e5), dtype=torch.float64)
    off = render_images(model, surf, drive, settings=RenderSettings(exposure=1e5, attached_shadows=False),
                        dtype=torch.float64)
    ref_off = shade(model.V, surf.normals, 1.0, drive, exposure=1e5, attached_shadows=False)
    np.testing.assert_allclose(off, ref_off, rtol=1e-10, atol=1e-12)
    assert (off < 0).any() and (on >= 0).all()
    np.testing.assert_array_equal(on, np.maximum(off, 0))  # one LED per pattern: max commutes


def test_renderer_reuses_the_surface_for_many_patterns(model):
    r = Renderer(model, RenderSettings(exposure=1e5))
    surf = sphere(SHAPE, PX, 2.0, 0.7)
    r.set_surface(surf)
    drive = mode_drive("point")
    batch = r.render(drive)
    one = np.stack([r.render(d) for d in drive])
    np.testing.assert_allclose(batch, one, rtol=1e-6)
    assert r.render(drive[3]).shape == SHAPE + (3,)


def test_auto_exposure_and_symmetry(model):
    """The ring is symmetric: a centred sphere under LED k and LED k+12 gives images rotated by 180 deg."""
    surf = sphere(SHAPE, PX, 2.0, 0.7)
    drive = mode_drive("point")
    mu = auto_exposure(model, drive, target_dn=200.0)
    img = render_images(model, surf, drive, settings=RenderSettings(exposure=mu), dtype=torch.float64)
    flat_img = render_images(model, None, drive, settings=RenderSettings(exposure=mu), dtype=torch.float64)
    assert flat_img.max() == pytest.approx(200.0, rel=1e-9)
    np.testing.assert_allclose(img[0], img[12][::-1, ::-1], rtol=1e-5, atol=1e-6 * img.max())


def test_bare_ring_matches_point_source(model):
    pos, axes = ring_geometry(24, 40.0)
    V = point_source_field(pos, axes, SHAPE, PX, 35.0)
    np.testing.assert_array_equal(model.V, V)


def test_input_checks_print_the_shape(model):
    r = Renderer(model)
    with pytest.raises(ValueError, match=r"\(P, 24, 3\).*\(3, 24\)"):
        r.render(np.ones((3, 24)))
    with pytest.raises(ValueError, match=r"surface has shape \(10, 10\)"):
        r.set_surface(sphere((10, 10), PX, 1.0, 0.2))
    with pytest.raises(ValueError, match="albedo"):
        r.set_surface(None, albedo=np.ones((2, 2)))
    with pytest.raises(ValueError, match="bit_depth"):
        RenderSettings(bit_depth=7)
    with pytest.raises(ValueError, match="V_depth"):
        Renderer(model, RenderSettings(depth_field=True))



@hsettings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), a=st.floats(0.0, 1.0), b=st.floats(0.0, 1.0),
       depth=st.floats(0.1, 1.4), cx=st.floats(-3.0, 3.0))
def test_superposition_of_light_property(model, seed, a, b, depth, cx):
    """Light adds: the frame under a*A + b*B is a*frame(A) + b*frame(B) (attached shadows are per LED)."""
    rng = np.random.default_rng(seed)
    A, B = rng.uniform(0, 1, (2, 24, 3))
    surf = sphere(SHAPE, PX, 1.5, depth, center=(cx, 0.3))
    r = Renderer(model, RenderSettings(exposure=1e5), dtype=torch.float64)
    r.set_surface(surf)
    both = r.render(a * A + b * B)
    np.testing.assert_allclose(both, a * r.render(A) + b * r.render(B), rtol=1e-10, atol=1e-12)
    assert np.all(np.isfinite(both)) and both.min() >= 0
