"""The conic lens top (sim/optics/conic.py) as physics: it is the ball at k = 0, its hits lie on the
sag formula, its normals are the surface's, a hyperbolic top of k = -n^2 focuses collimated light
from inside the lens to one point (the closed form of an aplanatic plano-hyperbolic lens), and a
traced scene with a conic top balances its energy."""

import math

import numpy as np
import pytest
import torch

from sim.optics.conic import ConicTop, conic_sag
from sim.optics.engine import EngineFallback, resolve_engine
from sim.optics.interface import refract
from sim.optics.sphere import Ball
from sim.scene import load_scene, scene_from_dict, scene_to_dict

torch.set_num_threads(1)


def _random_rays(n, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    o = tuple((torch.rand(n, generator=g, dtype=dtype) - 0.5) * s for s in (80.0, 80.0, 40.0))
    d = torch.randn(3, n, generator=g, dtype=dtype)
    d = d / d.norm(dim=0)
    return o, tuple(d)


def test_sphere_is_the_ball():
    o, d = _random_rays(20000, 0)
    ball, conic = Ball(600.0, 16.0), ConicTop(600.0, 16.0, 0.0)
    for f in ("entry", "exit"):
        a, b = getattr(ball, f)(o, d), getattr(conic, f)(o, d)
        fin = torch.isfinite(a)
        assert torch.equal(fin, torch.isfinite(b))
        assert float((a[fin] - b[fin]).abs().max()) < 1e-9
    t = ball.exit(o, d)
    m = torch.isfinite(t)
    p = tuple(a[m] + t[m] * b[m] for a, b in zip(o, d))  # points on the sphere
    for x, y in zip(ball.normal(p), conic.normal(p)):
        assert torch.allclose(x, y, atol=1e-12)


@pytest.mark.parametrize("k", [-4.0, -1.0, -0.5, 0.8])
def test_hits_lie_on_the_sag_and_normals_are_gradients(k):
    R, apex = 30.0, 16.0
    top = ConicTop(R, apex, k)
    o, d = _random_rays(20000, 1)
    hits = 0
    for f in ("entry", "exit"):
        t = getattr(top, f)(o, d)
        m = torch.isfinite(t) & (t.abs() < 1e3)
        p = tuple(oo[m] + t[m] * dd[m] for oo, dd in zip(o, d))
        rho = torch.sqrt(p[0] ** 2 + p[1] ** 2)
        # The part a lens uses: near the axis, and on an ellipsoid its upper half (the sag formula's branch).
        near = (rho < 20.0) & ((apex - p[2]) <= (R / (1.0 + k) if k > -1 else math.inf))
        sag = conic_sag(rho[near], R, k)
        ok = torch.isfinite(sag)
        assert float((apex - p[2][near][ok] - sag[ok]).abs().max()) < 1e-8
        assert bool((p[2] <= apex + 1e-9).all())  # never the other sheet of a hyperboloid
        hits += int(m.sum())
        # The normal is the surface's: perpendicular to the sag's meridian tangent, pointing up-out.
        n = top.normal(tuple(c[near][ok] for c in p))
        r = rho[near][ok]
        h = 1e-6
        slope = -(conic_sag(r + h, R, k) - conic_sag(r - h, R, k)) / (2 * h)  # dz/drho
        nr = (n[0] * p[0][near][ok] + n[1] * p[1][near][ok]) / r.clamp_min(1e-12)
        assert float((nr + slope * n[2]).abs()[r > 1e-3].max()) < 1e-6
        assert bool((n[2] > 0).all())
        assert float((n[0] ** 2 + n[1] ** 2 + n[2] ** 2 - 1).abs().max()) < 1e-12
    assert hits > 1000


def test_vertical_ray_on_a_paraboloid_uses_the_linear_case():
    top = ConicTop(10.0, 5.0, -1.0)
    o = (torch.tensor([0.0, 3.0], dtype=torch.float64), torch.zeros(2, dtype=torch.float64),
         torch.tensor([-20.0, -20.0], dtype=torch.float64))
    d = (torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    t = top.exit(o, d)
    assert t.tolist() == pytest.approx([25.0, 25.0 - 9.0 / 20.0])  # sag rho^2 / (2 R) = 0.45
    assert top.entry(o, d).tolist() == [-math.inf, -math.inf]


def test_hyperbolic_top_of_k_minus_n_squared_focuses_collimated_light():
    """A plano-hyperbolic lens with k = -n^2: light travelling along the axis inside the glass
    leaves the hyperbolic face aimed at one point, f = R / (n - 1) above the apex (no spherical
    aberration). A sphere of the same R misses that point by millimetres at the rim."""
    n, R, apex = 1.49, 20.0, 10.0
    rho = torch.linspace(0.5, 12.0, 40, dtype=torch.float64)
    o = (rho, torch.zeros_like(rho), torch.zeros_like(rho))
    d = (torch.zeros_like(rho), torch.zeros_like(rho), torch.ones_like(rho))
    focus = {}
    for name, k in (("hyperbola", -n * n), ("sphere", 0.0)):
        top = ConicTop(R, apex, k)
        t = top.exit(o, d)
        p = tuple(a + t * b for a, b in zip(o, d))
        nrm = top.normal(p)
        out, _, _, tir = refract(d, tuple(-c for c in nrm), n)
        assert not bool(tir.any())
        s = -p[0] / out[0]  # where each ray crosses the axis
        focus[name] = p[2] + s * out[2]
    assert float((focus["hyperbola"] - (apex + R / (n - 1))).abs().max()) < 1e-9
    assert float((focus["sphere"] - (apex + R / (n - 1))).abs().max()) > 1.0


def test_scene_with_a_conic_top_loads_draws_and_balances_energy():
    from sim.lens_design import trace_report

    d = scene_to_dict(load_scene("default"))
    d["lens"]["top"].update(radius=200.0, conic=-3.0)
    s = scene_from_dict(d)
    assert s.lens.top_conic == -3.0
    rho = np.linspace(0.0, s.lens.rim_rho, 7)
    assert np.allclose(s.lens.top_z(rho), s.lens.apex_z - conic_sag(rho, 200.0, -3.0))
    assert np.allclose(s.lens.top_rho(s.lens.top_z(rho)), rho, atol=1e-9)
    assert s.lens.rim_z < s.lens.apex_z and abs(s.lens.side_rho(s.lens.rim_z) - s.lens.top_rho(s.lens.rim_z)) < 1e-9
    with pytest.warns(EngineFallback, match="conic"):  # the kernel traces no conic: torch does, and says so
        r = trace_report(s, rays=20000, sampler="sobol", dtype=torch.float64)
    assert r["energy_residual"] < 1e-12 and 0 < r["fraction_on_screen"] < 1 and r["engine"] == "torch"
    assert scene_from_dict(scene_to_dict(s)).lens == s.lens  # round trip keeps the conic
    with pytest.raises(ValueError, match="kernel engine does not trace this lens's conic surface"):
        resolve_engine("kernel", "robust", s)


def test_every_lens_surface_says_which_engines_trace_it():
    """The torch tracer's lens is made of the classes sim.optics.surfaces names for the scene's
    surfaces; every kind names a class that exists, and the kernel's kinds are the ones it
    implements (no conic)."""
    from sim.optics.lens import LensBody
    from sim.optics.surfaces import SURFACES, lens_surfaces

    d = scene_to_dict(load_scene("default"))
    d["lens"]["top"].update(radius=200.0, conic=-3.0)
    for lens in (load_scene("default").lens, scene_from_dict(d).lens):
        body = LensBody(lens)
        for kind, surface in zip(lens_surfaces(lens), body.sets):
            module, _, cls = SURFACES[kind].target.partition(":")
            assert type(surface).__module__ == module and type(surface).__name__ == cls
    assert {k for k, s in SURFACES.items() if "kernel" in s.engines} == {"swept_arc", "cylinder", "sphere", "plane"}


def test_cylinder_rim_on_a_conic_top_and_a_clear_error_past_an_ellipsoid():
    from pipeline.base.errors import UserError

    d = scene_to_dict(load_scene("plano-sphere"))
    d["lens"]["top"].update(radius=600.0, conic=-1.0)
    s = scene_from_dict(d)
    assert s.lens.rim_z == pytest.approx(s.lens.apex_z - 25.0 ** 2 / 1200.0)
    d["lens"]["top"].update(radius=30.0, conic=3.0)  # an ellipsoid only 15 mm wide
    with pytest.raises(UserError, match="lens/side/cylinder_radius"):
        scene_from_dict(d)
