"""Each effect on and off (off = not computed), and each effect against its own physics."""

import math

import numpy as np
import pytest
import torch

from pipeline.base.frames import optical_to_recon, pixel_to_recon
from pipeline.base.modes import mode_drive
from sim.geometry import sphere
from sim.point_source import point_source_field, ring_geometry
from sim.render import EFFECTS, IMAGE_EFFECTS, Renderer, RenderSettings, bare_ring_illumination, render_images

SHAPE = (24, 32)
PX = 0.25
MU = 2e5

ON = {
    "depth_field": dict(depth_field=True),
    "attached_shadows": dict(attached_shadows=True),
    "specular": dict(specular=0.04, roughness=0.3),
    "cast_shadows": dict(cast_shadows=True),
    "crosstalk": dict(crosstalk=[[0.9, 0.1, 0.0], [0.05, 0.9, 0.05], [0.0, 0.2, 0.8]]),
    "vignetting": dict(vignetting=0.5),
    "distortion": dict(distortion=(0.2, 0.05)),
    "dark_level": dict(dark_level=10.0),
    "shot_noise": dict(shot_noise=0.5),
    "read_noise": dict(read_noise=2.0),
    "saturation": dict(saturation=True, full_scale=100.0),
    "quantization": dict(bit_depth=8),
}
# The function that does each effect's work; patched to raise when the effect is off.
WORKER = {"depth_field": "_depth_field", "specular": "_specular_lobe", "cast_shadows": "_cast_visibility",
          "vignetting": "_make_vignette",
          "distortion": "_make_distortion_grid"}


@pytest.fixture(scope="module")
def model():
    return bare_ring_illumination(SHAPE, PX, depth_heights=[0.0, 0.5, 1.0, 1.5])


@pytest.fixture(scope="module")
def surf():
    return sphere(SHAPE, PX, radius=1.5, depth=1.0, center=(0.5, 0.2))


def _off(name):
    kw = {"attached_shadows": name == "attached_shadows"}
    kw.update(ON[name] if name else {})
    return kw


@pytest.mark.parametrize("name", EFFECTS)
def test_each_effect_on_changes_the_image_and_off_is_not_computed(name, model, surf, monkeypatch):
    drive = mode_drive("point")[:6]
    base = RenderSettings(exposure=MU, attached_shadows=False)
    r_off = Renderer(model, base)
    r_off.set_surface(surf)
    img_off = r_off.render(drive)
    assert r_off.computed == []
    r_on = Renderer(model, RenderSettings(exposure=MU, **{"attached_shadows": False, **ON[name]}))
    r_on.set_surface(surf)
    img_on = r_on.render(drive)
    assert r_on.computed == [name]
    assert not np.array_equal(img_on.astype(np.float64), img_off.astype(np.float64))
    # Off means not computed: the effect's code must not run at all.
    def boom(*a, **k):
        raise AssertionError(f"{name} computed although off")

    for effect in EFFECTS:
        if effect in IMAGE_EFFECTS:
            monkeypatch.setattr(Renderer, f"_fx_{effect}", boom)
        if effect in WORKER:
            monkeypatch.setattr(Renderer, WORKER[effect], boom)
    monkeypatch.setattr(torch, "randn", boom)
    r = Renderer(model, base)
    r.set_surface(surf)
    np.testing.assert_array_equal(r.render(drive), img_off)


def test_quantization_and_saturation_bounds(model, surf):
    drive = mode_drive("monochromatic")
    flt = render_images(model, surf, drive, settings=RenderSettings(exposure=MU))
    for bits, dtype in [(8, np.uint8), (10, np.uint16), (12, np.uint16), (16, np.uint16)]:
        top = 2 ** bits - 1
        scale = 0.8 * top / flt.max()  # below full scale: pure rounding
        q = render_images(model, surf, drive, settings=RenderSettings(exposure=MU * scale, bit_depth=bits))
        assert q.dtype == dtype
        f = render_images(model, surf, drive, settings=RenderSettings(exposure=MU * scale))
        assert np.abs(q - f.astype(np.float64)).max() <= 0.5 + 1e-3 * top * 1e-3
        # ten times over full scale: clipped exactly at 2^b - 1, never wrapped around
        sat = render_images(model, surf, drive, settings=RenderSettings(exposure=MU * scale * 10, bit_depth=bits,
                                                                      read_noise=3.0))
        assert sat.max() == top and sat.min() >= 0
        assert (sat == top).mean() > 0.5
    # float output with saturation: clipped at full_scale, negative noise clipped at 0
    s = RenderSettings(exposure=MU, saturation=True, full_scale=50.0, read_noise=20.0)
    out = render_images(model, None, drive, settings=s)
    assert out.max() == 50.0 and out.min() == 0.0


def test_seeded_noise_is_reproducible_and_has_the_right_statistics(model):
    drive = np.ones((1, 24, 3))
    s = RenderSettings(exposure=MU, read_noise=2.0, shot_noise=0.5, seed=7)
    a = render_images(model, None, drive, settings=s)
    b = render_images(model, None, drive, settings=s)
    c = render_images(model, None, drive, settings=s, seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    clean = render_images(model, None, drive, settings=RenderSettings(exposure=MU))
    # residual variance = read^2 + gain * signal, checked on many seeded frames
    res = np.stack([render_images(model, None, drive, settings=s, seed=k) for k in range(20)]) - clean
    expected_var = 4.0 + 0.5 * clean
    z = (res ** 2).mean(axis=0) / expected_var
    assert abs(z.mean() - 1.0) < 0.02
    assert abs(res.mean()) < 0.05


def test_cast_shadows_match_ray_sphere_intersection():
    """On the flat gel around a ball, a pixel is shadowed from LED i iff the segment to the LED hits the ball."""
    shape, px = (40, 48), 0.1
    model = bare_ring_illumination(shape, px, gel_z=12.0, radius=20.0, cone_half_angle_deg=89.0)
    R, d = 1.0, 0.9
    surf = sphere(shape, px, R, d)
    r = Renderer(model, RenderSettings(cast_shadows=True, cast_shadow_step_px=0.5))
    vis = r._cast_visibility(surf).numpy().reshape(24, *shape)
    rows, cols = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    x, y = pixel_to_recon(rows, cols, shape, px)
    leds = optical_to_recon(model.led_positions) + np.array([0, 0, model.gel_z])
    c = np.array([0.0, 0.0, d - R])
    flat_px = ~surf.contact
    agree = []
    for i in range(24):
        P = np.stack([x, y, np.zeros_like(x)], -1)
        D = leds[i] - P
        # |P + tD - c|^2 = R^2, t in (0, 1]
        f = P - c
        a = (D * D).sum(-1)
        b = 2 * (f * D).sum(-1)
        cc = (f * f).sum(-1) - R * R
        disc = b * b - 4 * a * cc
        sq = np.sqrt(np.maximum(disc, 0))
        t1, t2 = (-b - sq) / (2 * a), (-b + sq) / (2 * a)
        hit = (disc > 0) & (t2 > 0) & (t1 <= 1)
        shadow_true = hit & flat_px
        shadow = (vis[i] == 0) & flat_px
        agree.append((shadow == shadow_true)[flat_px].mean())
        assert shadow_true.sum() > 10  # the test has shadows to find
    assert min(agree) > 0.985, agree
    # a convex cap never shadows itself: on the cap only attached shadows remain
    V = model.V.reshape(24, -1, 3)
    lit = np.einsum("lxk,xk->lx", V, surf.normals.reshape(-1, 3)).reshape(24, *shape) > 1e-3 * V[..., 2].max()
    assert ((vis == 0) & lit & surf.contact[None]).mean() < 0.002


def test_depth_field_matches_the_field_at_the_displaced_surface(surf):
    heights = np.linspace(0.0, 1.2, 13)
    model = bare_ring_illumination(SHAPE, PX, depth_heights=heights)
    s = RenderSettings(exposure=MU, depth_field=True)
    img = render_images(model, surf, mode_drive("point"), settings=s, dtype=torch.float64)
    pos, axes = ring_geometry(24, 40.0)
    Vx = point_source_field(pos, axes, SHAPE, PX, 35.0, gel_height=surf.height, dtype=np.float64)
    exact = MU / math.pi * np.maximum(np.einsum("lhwk,hwk->lhw", Vx, surf.normals), 0)  # (L, H, W), white LED
    np.testing.assert_allclose(img[..., 0], exact, rtol=2e-4, atol=1e-6 * exact.max())
    # and the effect matters at this depth: 1 mm closer to the LEDs changes the image by ~1%
    plain = render_images(model, surf, mode_drive("point"), settings=RenderSettings(exposure=MU), dtype=torch.float64)
    assert np.abs(plain[..., 0] - exact).max() > 5e-3 * exact.max()


def test_crosstalk_vignetting_distortion_dark(model, surf):
    drive = mode_drive("trichromatic")
    base = render_images(model, surf, drive, settings=RenderSettings(exposure=MU), dtype=torch.float64)
    C = np.array([[0.9, 0.1, 0.0], [0.05, 0.9, 0.05], [0.0, 0.2, 0.8]])
    xt = render_images(model, surf, drive, settings=RenderSettings(exposure=MU, crosstalk=C), dtype=torch.float64)
    np.testing.assert_allclose(xt, np.einsum("jk,phwk->phwj", C, base), rtol=1e-12)
    ident = render_images(model, surf, drive, settings=RenderSettings(exposure=MU, crosstalk=np.eye(3)),
                          dtype=torch.float64)
    np.testing.assert_allclose(ident, base, rtol=1e-12)
    a = 0.5
    vg = render_images(model, surf, drive, settings=RenderSettings(exposure=MU, vignetting=a), dtype=torch.float64)
    np.testing.assert_allclose(vg[0, 0, 0], base[0, 0, 0] / (1 + a) ** 2, rtol=1e-9)  # corner: r = 1
    assert (vg <= base + 1e-9).all()
    dk = render_images(model, surf, drive, settings=RenderSettings(exposure=MU, dark_level=16.0), dtype=torch.float64)
    np.testing.assert_allclose(dk - base, 16.0, rtol=1e-9)
    dark = render_images(model, surf, np.zeros((24, 3)), settings=RenderSettings(exposure=MU, dark_level=16.0))
    assert np.all(dark == 16.0)
    # distortion: zero coefficients are the identity; k1 > 0 (pincushion) pushes an off-axis bump outward
    z = render_images(model, surf, drive, settings=RenderSettings(exposure=MU, distortion=(0.0, 0.0)),
                      dtype=torch.float64)
    np.testing.assert_allclose(z, base, rtol=1e-9, atol=1e-9 * base.max())
    off = sphere(SHAPE, PX, 0.8, 0.4, center=(2.0, 0.0))
    flat_i = render_images(model, None, drive, settings=RenderSettings(exposure=MU), dtype=torch.float64)
    col = np.arange(SHAPE[1])

    def centroid(dist):
        img = render_images(model, off, drive, settings=RenderSettings(exposure=MU, distortion=dist),
                            dtype=torch.float64)
        ref = render_images(model, None, drive, settings=RenderSettings(exposure=MU, distortion=dist),
                            dtype=torch.float64)
        wgt = np.abs(img - ref).sum(axis=(0, 1, 3))
        return (wgt * col).sum() / wgt.sum()

    assert flat_i.shape == base.shape
    assert centroid((0.3, 0.0)) > centroid(None) + 0.3 > centroid((-0.3, 0.0)) + 0.6
