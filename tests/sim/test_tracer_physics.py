"""The tracer as physics: closed form, energy, symmetry, precision, seeds, instrumentation.

Every test runs both engines: the eager torch reference and the compiled kernel
(``tests/sim/test_tracer_kernel.py`` compares the two ray by ray).
"""

import numpy as np
import pytest
import torch

from pipeline.base.frames import optical_to_recon
from sim.optics import instrument
from sim.optics.binning import PixelGrid
from sim.optics.multisource import trace_all
from sim.optics.tracer import trace_source
from sim.point_source import point_source_field, ring_geometry
from sim.scene import load_scene, scene_from_dict, scene_to_dict

# Two cores shared by several test runs: a second intra-op thread mostly waits on barriers
# (measured 4-10x slower per op under that load), so the tracer tests run single-threaded.
torch.set_num_threads(1)

ENGINES = ["torch", "kernel"]



# These tests exercise the swept-arc side through which the LEDs' rays enter the lens of the
# previous default scene (default-v1); the current default's LEDs sit under its bottom face.

def bare_scene(count=3, radius=10.0, m=1.0, cone=60.0, z=20.0, tilt=0.0):
    d = scene_to_dict(load_scene("default-v1"))
    d.pop("lens")
    d["leds"].update(count=count, radius=radius, emission_m=m, cone_half_angle_deg=cone, rgb=[[1, 1, 1]],
                     tilt_deg=tilt)
    d["imaging_plane"] = {"z": z, "size": [40.0, 40.0], "resolution": [10, 10]}
    d["effects"] = ["emission_profile"]
    return scene_from_dict(d)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("tilt", [0.0, 25.0])
def test_bare_point_source_matches_closed_form(device, tilt, engine):
    """No lens: traced V equals the closed-form near field, averaged over each pixel, within MC error."""
    if engine == "kernel" and device == "cuda":
        pytest.skip("the kernel's CUDA path is tested in test_tracer_kernel.py (numba.cuda, not torch)")
    s = bare_scene(tilt=tilt)
    shape, pitch, sup = (10, 10), 4.0, 8
    res = trace_all(s, PixelGrid(shape, (pitch, pitch), s.plane.z), method="hits", rays=400_000,
                    sampler="sobol", device=device, engine=engine)
    V = optical_to_recon(res.V[0]).astype(np.float64)  # (L, H, W, 3)
    pos, axes = ring_geometry(3, 10.0, tilt_deg=tilt)
    fine = point_source_field(pos, axes, (shape[0] * sup, shape[1] * sup), pitch / sup, s.plane.z, m=1.0,
                              cone_half_angle_deg=60.0, dtype=np.float64)
    ref = fine.reshape(3, shape[0], sup, shape[1], sup, 3).mean(axis=(2, 4))
    err = np.linalg.norm(V - ref) / np.linalg.norm(ref)
    assert err < 0.02, err
    # and the flat-gel irradiance is n . V with n = +z (reconstruction frame)
    assert np.allclose(res.E[0].astype(np.float64), V[..., 2], rtol=1e-4, atol=1e-12)


@pytest.mark.parametrize("engine", ENGINES)
def test_isotropic_emitter_without_profile_effect(engine):
    """Emission profile disabled = isotropic inside the cone (m = 0), against the closed form."""
    s = bare_scene(count=1, radius=0.0, m=3.0, cone=45.0)
    s = s.with_effects(remove=["emission_profile"])
    res = trace_all(s, PixelGrid((10, 10), (4.0, 4.0), s.plane.z), rays=200_000, sampler="sobol", engine=engine)
    E = res.E[0, 0].astype(np.float64)
    fine = point_source_field(np.zeros((1, 3)), np.array([[0, 0, 1.0]]), (80, 80), 0.5, s.plane.z, m=0.0,
                              cone_half_angle_deg=45.0, dtype=np.float64)[0, ..., 2]
    ref = fine.reshape(10, 8, 10, 8).mean(axis=(1, 3))
    assert np.linalg.norm(E - ref) / np.linalg.norm(ref) < 0.03


@pytest.mark.parametrize("engine", ENGINES)
def test_energy_conservation(dtype, engine):
    tol = dtype.tol(1e-12, 2e-6)
    s = load_scene("default-v1").with_effects(add=["internal_bounces"])
    r = trace_source(s, rays=40_000, sampler="random", dtype=dtype.torch, engine=engine)
    e = r.energy
    assert abs(e.residual) < tol, e.as_dict()
    assert min(e.on_screen, e.elsewhere, e.reflected, e.absorbed) >= 0 and e.reflected > 0.01
    assert r.counters["tir_bounces"] > 0
    # Without Fresnel nothing is reflected; without the lens nothing is reflected or absorbed.
    e2 = trace_source(s.with_effects(remove=["fresnel"]), rays=20_000, dtype=dtype.torch, engine=engine).energy
    assert e2.reflected == 0.0 and abs(e2.residual) < tol
    e3 = trace_source(s.with_effects(remove=["lens"]), rays=20_000, engine=engine).energy
    assert e3.reflected == 0.0 and e3.absorbed == 0.0 and abs(e3.residual) < 1e-6


@pytest.mark.parametrize("engine", ENGINES)
def test_lens_changes_the_light_and_fresnel_losses_are_physical(engine):
    s = load_scene("plano-sphere")
    e = trace_source(s, rays=40_000, engine=engine).energy
    # Two near-normal PMMA interfaces reflect about 2 x 3.9 % (more at oblique incidence).
    assert 0.07 < e.reflected < 0.12
    assert abs(e.residual) < 1e-6


@pytest.mark.parametrize("engine", ENGINES)
def test_ring_symmetry(engine):
    s = load_scene("default-v1")
    g = PixelGrid((24, 24), (2.5, 2.5), s.plane.z)
    hits = trace_all(s, g, method="hits", rays=40_000, engine=engine)
    E = hits.E[0].astype(np.float64)
    # LED 0 (on +x) is mirror-symmetric about the x axis: rows flip (y -> -y), grid sampler.
    assert np.abs(E[0] - E[0][::-1, :]).sum() < 1e-4 * E[0].sum()
    # Every LED traced on its own equals LED 0's rays rotated (24-fold symmetry of ring + lens).
    own = trace_all(s, g, method="trace", rays=40_000, leds=[0, 5, 13], engine=engine).E[0].astype(np.float64)
    for k, i in enumerate([0, 5, 13]):
        assert np.abs(own[k] - E[i]).sum() < 1e-3 * E[i].sum()
    # The 24-LED image is invariant under 90 degree rotations and both mirror flips.
    tot = E.sum(0)
    for img in (np.rot90(tot), tot[::-1, :], tot[:, ::-1]):
        assert np.abs(img - tot).sum() < 1e-3 * tot.sum()
    # The paper's image rotation is close to exact for 90 degrees, worse for 15 (interpolation).
    rot = trace_all(s, g, method="image", rays=40_000, leds=[1, 6], engine=engine)
    img = rot.E[0].astype(np.float64)
    e15 = np.abs(img[0] - E[1]).sum() / E[1].sum()
    e90 = np.abs(img[1] - E[6]).sum() / E[6].sum()
    assert e90 < 1e-3 < e15
    # ... and its V vectors turn with the image (LED 6 sits on +y: its light comes from +y).
    V6 = hits.V[0, 6].astype(np.float64)
    assert np.abs(rot.V[0, 1].astype(np.float64) - V6).sum() < 1e-3 * np.abs(V6).sum()


@pytest.mark.parametrize("engine", ENGINES)
def test_float32_matches_float64(engine):
    s = load_scene("default-v1")
    g = PixelGrid((20, 20), (3.0, 3.0), s.plane.z)
    r32 = trace_all(s, g, rays=40_000, leds=[0], dtype=torch.float32, engine=engine)
    r64 = trace_all(s, g, rays=40_000, leds=[0], dtype=torch.float64, engine=engine)
    e32, e64 = r32.traces[0].energy, r64.traces[0].energy
    assert abs(e32.on_screen - e64.on_screen) < 1e-4 and abs(e32.reflected - e64.reflected) < 1e-5
    a, b = r32.E.astype(np.float64), r64.E
    assert np.abs(a - b).sum() < 2e-3 * b.sum()
    va, vb = r32.V.astype(np.float64), r64.V
    assert np.abs(va - vb).sum() < 2e-3 * np.abs(vb).sum()


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("sampler", ["random", "stratified", "sobol"])
def test_seeded_reproducible(sampler, engine):
    s = load_scene("default-v1")
    g = PixelGrid((10, 10), (5.0, 5.0), s.plane.z)
    a = trace_all(s, g, rays=10_000, sampler=sampler, seed=3, leds=[0], engine=engine).E
    b = trace_all(s, g, rays=10_000, sampler=sampler, seed=3, leds=[0], engine=engine).E
    c = trace_all(s, g, rays=10_000, sampler=sampler, seed=4, leds=[0], engine=engine).E
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_chunking_does_not_change_the_result():
    """The torch engine's chunks (the kernel's threads: test_tracer_kernel.py)."""
    s = load_scene("default-v1")
    g = PixelGrid((10, 10), (5.0, 5.0), s.plane.z)
    a = trace_all(s, g, rays=20_000, sampler="sobol", leds=[0], chunk=1 << 20, engine="torch")
    b = trace_all(s, g, rays=20_000, sampler="sobol", leds=[0], chunk=3000, engine="torch")
    assert np.allclose(a.E, b.E, rtol=1e-4, atol=1e-9) and np.allclose(a.V, b.V, rtol=1e-4, atol=1e-9)


@pytest.mark.parametrize("engine", ENGINES)
def test_disabled_effects_are_not_computed(engine):
    """Instrumentation: only the effects a scene lists run."""
    from sim.synthesize import synthesize

    bare = load_scene("default-v1").with_effects(remove=["lens", "fresnel", "emission_profile"])
    instrument.reset()
    synthesize(bare, (4, 4), 5.0, rays=2000, engine=engine)
    ran = instrument.snapshot()
    for effect in ("lens", "fresnel", "emission_profile", "internal_bounces", "dispersion", "depth_field"):
        assert ran.get(effect, 0) == 0, (effect, ran)
    full = load_scene("default-v1").with_effects(add=["internal_bounces", "dispersion", "depth_field"])
    instrument.reset()
    synthesize(full, (4, 4), 5.0, rays=2000, engine=engine)
    ran = instrument.snapshot()
    for effect in ("lens", "fresnel", "emission_profile", "internal_bounces", "dispersion", "depth_field"):
        assert ran.get(effect, 0) > 0, (effect, ran)


@pytest.mark.parametrize("engine", ENGINES)
def test_quarter_turn_shortcut_equals_direct_binning(engine):
    """24 angles on a square centred grid are binned 6 times plus exact rot90s: same images."""
    from sim.optics.binning import FieldAccumulator
    from sim.optics.multisource import led_azimuths

    s = load_scene("default-v1")
    az = led_azimuths(s)
    a = FieldAccumulator(PixelGrid((16, 16), (3.0, 3.0), s.plane.z), az)
    b = FieldAccumulator(PixelGrid((16, 16), (3.0, 3.0 * (1 + 1e-12)), s.plane.z), az)  # not square: direct
    assert len(a.binned) == 6 and len(b.binned) == 24
    trace_source(s, [a, b], rays=20_000, engine=engine)
    (Ea, Va), (Eb, Vb) = a.images(), b.images()
    assert float((Ea - Eb).abs().sum()) < 1e-3 * float(Eb.sum())  # a few rays on pixel edges may flip
    assert float((Va - Vb).abs().sum()) < 1e-3 * float(Vb.abs().sum())


@pytest.mark.parametrize("engine", ENGINES)
def test_channel_separated_metrics_and_eq15(engine):
    """Per-channel uniformity after channel separation, for a trichromatic ring (eq. 15)."""
    from sim.lens_design import trace_report
    from sim.optics.metrics import image_metrics, pattern_image

    d = scene_to_dict(load_scene("default-v1"))
    rgb = np.zeros((24, 3))
    rgb[:8, 0] = rgb[8:16, 1] = rgb[16:, 2] = 1.0  # three sectors lit R, G and B
    d["leds"]["rgb"] = rgb.tolist()
    d["imaging_plane"]["resolution"] = [20, 20]
    s = scene_from_dict(d)
    r = trace_report(s, rays=20_000, images=True, engine=engine)
    ch = r["channels"]
    # Each channel is lit from one side only: far less uniform than the white image.
    assert min(v["uniformity_cv"] for v in ch.values()) > r["uniformity_cv"]
    img = r["image"]
    # The R sector sits at azimuths 0..105 deg (+x, +y): the R image is brighter on that side.
    assert img[15:, 15:, 0].mean() > img[:5, :5, 0].mean()
    # eq. (15) is linear in exposure and brightness
    E = np.random.default_rng(0).random((24, 3, 3))
    assert np.allclose(pattern_image(E, rgb, np.full(24, 2.0), exposure=0.5), pattern_image(E, rgb))
    m = image_metrics(E, np.ones((24, 3)), np.full(24, 0.5))
    assert m["fraction_on_screen"] == 0.5 and m["channels"]["R"]["uniformity_cv"] == m["uniformity_cv"]


@pytest.mark.parametrize("engine", ENGINES)
def test_depth_field_matches_closed_form_at_each_height(engine):
    """V sampled at gel heights (toward the camera) equals the closed form on the displaced plane."""
    s = bare_scene(count=1, radius=10.0)
    heights = (0.0, 3.0)
    res = trace_all(s, PixelGrid((8, 8), (5.0, 5.0), s.plane.z), rays=300_000, sampler="sobol", heights=heights,
                    engine=engine)
    pos, axes = ring_geometry(1, 10.0)
    for k, h in enumerate(heights):
        V = optical_to_recon(res.V[k, 0]).astype(np.float64)
        fine = point_source_field(pos, axes, (64, 64), 5.0 / 8, s.plane.z, gel_height=np.full((64, 64), h),
                                  dtype=np.float64)[0]
        ref = fine.reshape(8, 8, 8, 8, 3).mean(axis=(1, 3))
        assert np.linalg.norm(V - ref) / np.linalg.norm(ref) < 0.02, h
    # Closer to the LEDs the field is stronger.
    assert float(res.E[1].sum()) > float(res.E[0].sum())


@pytest.mark.parametrize("engine", ENGINES)
def test_clear_aperture_absorbs_and_conserves_energy(engine):
    d = scene_to_dict(load_scene("default-v1"))
    d["lens"]["top"]["clear_aperture"] = 20.0
    s = scene_from_dict(d)
    a = trace_source(load_scene("default-v1"), rays=20_000, engine=engine)
    b = trace_source(s, rays=20_000, engine=engine)
    assert b.counters["aperture_absorbed"] > 0 and b.energy.absorbed > a.energy.absorbed
    assert b.energy.on_screen < a.energy.on_screen and abs(b.energy.residual) < 2e-6


@pytest.mark.parametrize("engine", ENGINES)
def test_tilted_ring_hit_rotation_is_exact(engine):
    d = scene_to_dict(load_scene("default-v1"))
    d["leds"]["tilt_deg"] = 20.0
    s = scene_from_dict(d)
    g = PixelGrid((12, 12), (5.0, 5.0), s.plane.z)
    hits = trace_all(s, g, method="hits", rays=20_000, engine=engine).E[0].astype(np.float64)
    own = trace_all(s, g, method="trace", rays=20_000, leds=[7], engine=engine).E[0, 0].astype(np.float64)
    assert np.abs(own - hits[7]).sum() < 1e-3 * own.sum()
