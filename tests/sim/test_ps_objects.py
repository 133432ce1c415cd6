"""Photometric-stereo test data: far-field lights and their cast shadows, the specular lobe's
physics, and the synthetic captures (and ``iristac sim ps-object``)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.ndimage import map_coordinates

from helpers import run_cli
from pipeline.base.store import read_record, write_record
from sim.far_field import dome_lights, far_field_illumination, far_field_visibility
from sim.ps_objects import bumpy_object, render_ps_capture, sphere_object
from sim.render import Renderer, RenderSettings
from sim.specular import ggx_brdf, specular_shading


def test_dome_lights_span_45_degrees_like_the_benchmark():
    d, e = dome_lights()
    assert d.shape == (96, 3) and e.shape == (96, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    angles = np.degrees(np.arccos(d[:, 2]))
    assert abs(angles.max() - 45.0) < 1e-9 and angles.min() > 1.0
    np.testing.assert_allclose(d.sum(0)[:2], 0.0, atol=1e-12)  # symmetric grid
    assert e.min() >= 0.6 * 0.95 and e.max() <= 1.0 * 1.05
    with pytest.raises(ValueError, match="at least 3 lights"):
        dome_lights(1, 2)


def _ray_hits_ball(px, py, d, R):
    """Does the ray from (px, py, 0) along d hit the ball of radius R centred at the origin?"""
    pd = px * d[0] + py * d[1]
    disc = pd * pd - (px * px + py * py - R * R)
    return (disc > 0) & (-pd + np.sqrt(np.clip(disc, 0, None)) > 0), disc


def test_cast_shadows_of_a_ball_on_the_table_match_ray_sphere_intersection():
    R, size = 14.0, 64
    obj = sphere_object((size, size), R)
    d, _ = dome_lights(3, 4, 45.0)
    vis = far_field_visibility(obj.field.height, d, 1.0, dtype=torch.float64).numpy().reshape(len(d), size, size)
    c = (size - 1) / 2
    yy, xx = np.mgrid[0:size, 0:size]
    x, y = xx - c, -(yy - c)  # reconstruction frame, 1 mm pixels
    checked = 0
    for i, di in enumerate(d):
        hit, _ = _ray_hits_ball(x, y, di, R)
        # closest approach of the ray's line to the centre: pixels within a pixel of the
        # shadow's edge, and the ball's own rim, are left out (sampling decides them)
        pd = x * di[0] + y * di[1]
        miss = np.sqrt(np.clip(x * x + y * y - pd * pd, 0, None))
        table = (np.hypot(x, y) > R + 1.5) & (np.abs(miss - R) > 1.5)
        assert (vis[i][table] == (~hit[table]).astype(float)).all(), i
        checked += int(table.sum())
        # on the ball, where the light is in front of the surface, a convex shape casts no shadow
        n = obj.field.normals
        front = obj.mask & ((n @ di) > 0.2)
        assert (vis[i][front] == 1).all()
    assert checked > 20000


def _brute_visibility(h, d, step=0.05):
    """Reference: march every pixel's ray in small steps with cubic interpolation (scipy)."""
    H, W = h.shape
    rows, cols = np.mgrid[0:H, 0:W].astype(float)
    dcol, drow, dz = d[0], -d[1], d[2]
    horiz = math.hypot(dcol, drow)
    if horiz < 1e-12:
        return np.ones((H, W))
    blocked = np.zeros((H, W), bool)
    rise = dz / horiz
    t = step
    while t * rise <= h.max() - h.min() + 1.0:
        r, c = rows + t * drow / horiz, cols + t * dcol / horiz
        s = map_coordinates(h, [r, c], order=1, mode="constant", cval=0.0)
        blocked |= s > h + t * rise + 0.25
        t += step
    return (~blocked).astype(float)


def test_bumpy_visibility_matches_a_fine_brute_force_march():
    obj = bumpy_object((48, 48), 21, bumps=8, seed=3)
    d, _ = dome_lights(2, 3, 45.0)
    vis = far_field_visibility(obj.field.height, d, 1.0, dtype=torch.float64).numpy().reshape(len(d), 48, 48)
    shadowed_inside = 0
    for i, di in enumerate(d):
        ref = _brute_visibility(obj.field.height, di)
        assert (vis[i] != ref).mean() < 0.01, (i, (vis[i] != ref).mean())
        lit_face = obj.mask & ((obj.field.normals @ di) > 0)
        shadowed_inside += int(((vis[i] == 0) & lit_face).sum())
    assert shadowed_inside > 10  # the bumps do cast shadows on the object


def test_ggx_lobe_is_reciprocal_and_conserves_energy():
    rng = np.random.default_rng(0)
    a, b, h, vh = (torch.as_tensor(rng.uniform(0.05, 1, 50)) for _ in range(4))
    np.testing.assert_allclose(ggx_brdf(a, b, h, vh, 0.4, 0.5), ggx_brdf(b, a, h, vh, 0.4, 0.5), rtol=1e-12)
    # Directional albedo of the lobe with F0 = 1: integral of f cos(theta_l) over the hemisphere
    # is at most 1 (Smith shadowing loses a little), for a viewer 0 and 40 degrees off the normal.
    th, ph = np.meshgrid(np.linspace(0, np.pi / 2, 800, endpoint=False) + np.pi / 3200,
                         np.linspace(0, 2 * np.pi, 400, endpoint=False), indexing="ij")
    dA = (np.pi / 2 / 800) * (2 * np.pi / 400) * np.sin(th)
    l = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    for view_deg, rough in [(0, 0.3), (40, 0.3), (0, 0.6)]:
        v = np.array([math.sin(math.radians(view_deg)), 0.0, math.cos(math.radians(view_deg))])
        hv = l + v
        hv /= np.linalg.norm(hv, axis=-1, keepdims=True)
        t = lambda x: torch.as_tensor(x)  # noqa: E731
        f = ggx_brdf(t(l[..., 2]), t(np.full(th.shape, v[2])), t(hv[..., 2]), t(hv @ v), rough, 1.0).numpy()
        albedo = float((f * l[..., 2] * dA).sum())
        assert 0.75 < albedo <= 1.0 + 1e-3, (view_deg, rough, albedo)


def test_highlight_sits_at_the_half_vector():
    obj = sphere_object((81, 81), 38)
    d = np.array([[0.5, 0.2, math.sqrt(1 - 0.29)]])
    model = far_field_illumination(d, obj.field.shape, 1.0)
    r = Renderer(model, RenderSettings(exposure=1.0, specular=0.5, roughness=0.15), dtype=torch.float64)
    r.set_surface(obj.field, 0.0)  # black albedo: only the lobe
    img = r.render(np.ones((1, 1, 3)))[0, ..., 0]
    peak = np.unravel_index(np.argmax(img), img.shape)
    h = d[0] + [0, 0, 1]
    h /= np.linalg.norm(h)
    ang = math.degrees(math.acos(np.clip(obj.field.normals[peak] @ h, -1, 1)))
    assert ang < 2.0, ang  # within about a pixel's normal change
    # per-pixel materials: a matte half renders exactly the Lambertian image
    spec = np.where(np.arange(81)[None, :] < 40, 0.0, 0.5) * np.ones((81, 1))
    r.set_surface(obj.field, 0.7, specular=spec)
    mixed = r.render(np.ones((1, 1, 3)))[0]
    lam = Renderer(model, RenderSettings(exposure=1.0), dtype=torch.float64)
    lam.set_surface(obj.field, 0.7)
    np.testing.assert_allclose(mixed[:, :40], lam.render(np.ones((1, 1, 3)))[0][:, :40], rtol=1e-12)
    with pytest.raises(ValueError, match="specular effect"):
        lam.set_surface(obj.field, 0.7, specular=spec)


def test_specular_shading_float32_matches_float64():
    obj = bumpy_object((40, 40), 18, bumps=5)
    d, _ = dome_lights(3, 4)
    V = torch.as_tensor(np.broadcast_to(d.T[:, :, None], (3, 12, 1600)).copy())
    n = torch.as_tensor(obj.field.normals.reshape(-1, 3).T.copy())
    s64 = specular_shading(V, n, 0.3, 0.04)
    s32 = specular_shading(V.float(), n.float(), 0.3, 0.04)
    assert float((s32.double() - s64).abs().max()) < 1e-5 * float(s64.max())


def test_ps_capture_layout_highlights_and_shadows(tmp_path):
    obj = bumpy_object((48, 48), 20, bumps=6, amplitude=0.2)
    d, e = dome_lights(4, 6)
    rec = render_ps_capture(obj, d, e, specular=0.04, roughness=0.2, frame_shape=(60, 70), seed=4)
    assert "reference" not in rec.data and rec.data["frames"].shape == (1, 24, 60, 70, 3)
    assert rec.data["frames"].dtype == np.uint16 and rec.meta["bit_depth"] == 16
    m = rec.data["mask"]
    assert m.sum() == obj.mask.sum() and not m[:6].any()
    assert rec.data["frames"][0][:, ~m].max() < 200  # black background: noise only
    lv = rec.data["lights/light_vectors"]
    np.testing.assert_allclose(lv[:, 1], d * e[:, 1:2], rtol=1e-6)
    path = write_record(tmp_path / "ps.h5", rec)
    back = read_record(path, schema="capture")
    np.testing.assert_array_equal(back.data["frames"], rec.data["frames"])
    # highlights: brighter than any Lambertian pixel can be; cast shadows: dark where lit
    lam = render_ps_capture(obj, d, e, specular=0.0, cast_shadows=False, read_noise=0.0, shot_noise=0.0,
                            frame_shape=(60, 70), seed=4).data["frames"][0].astype(float)
    glossy = render_ps_capture(obj, d, e, specular=0.04, roughness=0.2, cast_shadows=False, read_noise=0.0,
                               shot_noise=0.0, frame_shape=(60, 70), seed=4).data["frames"][0].astype(float)
    shadowed = render_ps_capture(obj, d, e, specular=0.0, cast_shadows=True, read_noise=0.0, shot_noise=0.0,
                                 frame_shape=(60, 70), seed=4).data["frames"][0].astype(float)
    assert lam[:, m].max() <= 30000 * 1.0001 and glossy[:, m].max() > 1.3 * lam[:, m].max()
    assert ((shadowed < 0.5 * lam) & (lam > 1000))[:, m].sum() > 20


def test_cli_ps_object_json(tmp_path):
    r = run_cli("sim", "ps-object", "--object", "sphere", "--size", "32", "--radius-px", "12", "--lights", "3", "4",
                "--frame", "40", "50", "--out", tmp_path / "s.h5", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert set(out) == {"out", "object", "lights", "height", "width", "mask_pixels", "specular", "roughness",
                        "effects"}
    assert out["lights"] == 12 and (out["height"], out["width"]) == (40, 50) and "specular" in out["effects"]
    r = run_cli("sim", "ps-object", "--size", "20", "--radius-px", "30", "--out", tmp_path / "x.h5")
    assert r.returncode == 2 and "radius_px must fit" in r.stderr and not (tmp_path / "x.h5").exists()
