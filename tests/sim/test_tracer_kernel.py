"""The compiled kernel against the eager torch reference, its samplers, threads, hard rays and CUDA.

On the grid sampler both engines trace the same rays, so they agree to float rounding: energy
books to 1e-7, images to 1e-4 of their L1 norm (a ray within rounding of a pixel edge may land
on the other side), counters exactly. The kernel's random, stratified and Sobol samplers draw
their own points (counter-based, the same for any thread count), so there the agreement is
statistical. The physics tests (test_tracer_physics.py) run on both engines.
"""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim.optics import engine
from sim.optics import kernel as K
from sim.optics.grid import ImageBins, PixelGrid
from sim.optics.multisource import led_azimuths, trace_all
from sim.scene import load_scene, scene_from_dict, scene_to_dict

ROOT = Path(__file__).resolve().parents[2]


def _aperture_bounces_scene():
    d = scene_to_dict(load_scene("default"))
    d["lens"]["top"]["clear_aperture"] = 40.0
    return scene_from_dict(d).with_effects(add=["internal_bounces"])


@pytest.mark.parametrize("make, heights", [(lambda: load_scene("default"), (0.0,)),
                                           (_aperture_bounces_scene, (0.0, 1.5)),
                                           (lambda: load_scene("plano-sphere"), (0.0,))])
def test_kernel_matches_the_reference_ray_by_ray(make, heights):
    s = make()
    g = PixelGrid((24, 24), (2.5, 2.5), s.plane.z)
    a = trace_all(s, g, rays=60_000, heights=heights, engine="torch")
    b = trace_all(s, g, rays=60_000, heights=heights, engine="kernel")
    ea, eb = a.traces[0].energy.as_dict(), b.traces[0].energy.as_dict()
    for key in ea:
        assert abs(ea[key] - eb[key]) < 1e-7, (key, ea, eb)
    assert a.traces[0].counters == b.traces[0].counters
    assert b.E.sum() > 0 and np.abs(a.E - b.E).sum() < 1e-4 * a.E.sum()
    assert np.abs(a.V - b.V).sum() < 1e-4 * np.abs(a.V).sum()
    if "internal_bounces" in s.effects:
        assert b.traces[0].counters["tir_bounces"] > 0 and b.traces[0].counters["aperture_absorbed"] > 0


def test_random_sampler_agrees_statistically():
    """Independent random rays: the kernel's image differs from the reference's by Monte Carlo
    noise only (as much as two reference runs with different seeds differ), energies within 4 sigma."""
    s = load_scene("default")
    g = PixelGrid((12, 12), (5.0, 5.0), s.plane.z)
    n = 200_000
    t1 = trace_all(s, g, rays=n, sampler="random", seed=1, leds=[0], vector=False, engine="torch")
    t2 = trace_all(s, g, rays=n, sampler="random", seed=2, leds=[0], vector=False, engine="torch")
    k1 = trace_all(s, g, rays=n, sampler="random", seed=1, leds=[0], vector=False, engine="kernel")
    noise = np.linalg.norm(t1.E - t2.E)
    diff = np.linalg.norm(k1.E - t1.E)
    assert 0.5 * noise < diff < 1.6 * noise, (diff, noise)
    p = t1.traces[0].energy.on_screen
    sigma = math.sqrt(p * (1 - p) / n)
    assert abs(k1.traces[0].energy.on_screen - p) < 4 * math.sqrt(2) * sigma


def test_samplers_are_what_they_claim():
    s = load_scene("default")

    def points(kind, n, seed=0):
        P, F, seeds = engine.kernel_params(s, rays=n, sampler=kind, seed=seed, dtype="float64")
        Pt, Ft = K.as_tuple(P), K.as_tuple(F)
        return np.array([K.sample(Pt, Ft, seeds, i) for i in range(n)])

    # grid: the reference's cell centres exactly
    g = points("grid", 16)
    assert np.array_equal(g, np.array([((i + 0.5) / 4, (j + 0.5) / 4) for i in range(4) for j in range(4)]))
    # stratified: exactly one point in each cell of the k x k grid, jittered
    st = points("stratified", 64)
    cells = np.floor(st * 8).astype(int)
    assert np.array_equal(cells, np.array([(i, j) for i in range(8) for j in range(8)]))
    assert len(np.unique(st[:, 0])) == 64
    # Owen-scrambled Sobol is a (0, m, 2)-net: 256 points, one in every elementary interval
    sb = points("sobol", 256, seed=5)
    for a in range(9):
        b = 8 - a
        boxes = np.floor(sb[:, 0] * 2 ** a).astype(int) * 2 ** b + np.floor(sb[:, 1] * 2 ** b).astype(int)
        assert len(np.unique(boxes)) == 256, (a, b)
    assert not np.array_equal(sb, points("sobol", 256, seed=6))
    # random: uniform (chi-square over 10 x 10 cells, 100 dof: 99.9 % below 149)
    r = points("random", 20_000)
    counts = np.histogram2d(r[:, 0], r[:, 1], bins=10, range=[[0, 1], [0, 1]])[0]
    assert ((counts - 200) ** 2 / 200).sum() < 149
    assert (r >= 0).all() and (r < 1).all()


def test_thread_count_changes_only_rounding_and_runs_are_reproducible():
    s = load_scene("default")
    lay = [ImageBins(PixelGrid((16, 16), (3.5, 3.5), s.plane.z), led_azimuths(s)).layout]
    (a,), ra = engine.trace_led(s, lay, rays=30_000, sampler="sobol", threads=1)
    (b,), rb = engine.trace_led(s, lay, rays=30_000, sampler="sobol", threads=2)
    (c,), rc = engine.trace_led(s, lay, rays=30_000, sampler="sobol", threads=2)
    assert np.array_equal(b, c) and rb.energy == rc.energy
    # The slots split the rays into other blocks: a ray's lane in the vector loop (or its scalar
    # remainder) may round its last float32 bit differently; nothing more.
    assert np.allclose(a, b, rtol=1e-5, atol=1e-6 * float(np.abs(a).max()))
    for key, v in ra.energy.as_dict().items():
        assert abs(v - rb.energy.as_dict()[key]) < 1e-9
    assert ra.counters == rb.counters


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_block_exit_solve_matches_the_scalar_path_through_the_rounded_edge(dtype):
    """The default scene's rays leaving through the lens's rounded (swept-arc) edge take the block
    loops' masked exit solve; the scalar trace_ray (the reference's loops) must book them alike
    (most are totally reflected there: where the solve puts the exit decides that)."""
    s = load_scene("default")
    n = 40_000
    P, F, seeds = engine.kernel_params(s, rays=n, sampler="grid", dtype=dtype)
    Pt, Ft, tab = K.as_tuple(P), K.as_tuple(F), engine.grid_tables(P, F)
    D = np.array([K.emit(Pt, Ft, seeds, tab, i) for i in range(n)])
    O = np.broadcast_to(P[[K.P_SRC_X, K.P_SRC_Y, K.P_SRC_Z]], D.shape)
    r = engine.lens_rays(s, O, D, powers=np.full(n, 1.0 / n), dtype=dtype)
    q, d, w = r["origin"], r["direction"], r["power"]
    ln = s.lens
    # where a ray leaves, or is totally reflected and absorbed (no bounces followed): on the edge
    side = np.isin(r["code"], [K.OUT, K.TIR_LOST]) & (q[:, 2] > ln.bottom_z + 1e-3) & (q[:, 2] < ln.rim_z - 1e-3)
    t = (s.plane.z - q[:, 2]) / d[:, 2]
    x, y = q[:, 0] + t * d[:, 0], q[:, 1] + t * d[:, 1]
    on = (t > 0) & (np.abs(x) <= s.plane.size[0] / 2) & (np.abs(y) <= s.plane.size[1] / 2)
    # one ray in nine meets the edge from inside, nearly all beyond the critical angle
    assert side.mean() > 0.05 and r["absorbed"][side].sum() > 0.05 and (side & (w > 0)).any()
    _, tr = engine.trace_led(s, [], rays=n, sampler="grid", dtype=dtype, threads=1)
    e = tr.energy
    tol = 1e-5 if dtype == "float32" else 1e-9
    assert abs(e.reflected - r["reflected"].sum()) < tol and abs(e.absorbed - r["absorbed"].sum()) < tol
    assert abs(e.on_screen + e.elsewhere - w.sum()) < tol
    assert abs(e.on_screen - w[on].sum()) < 3.0 / n  # a ray within rounding of the gel's edge may flip
    assert tr.counters["tir_absorbed"] == int((r["code"] == K.TIR_LOST).sum())
    assert tr.counters["numerical_lost"] == int((r["code"] == K.LOST).sum())


def test_hard_rays_stay_finite():
    """Rays in planes through the axis, along the axis, tangent to the top, grazing the side, from
    inside the lens and backwards: every output finite and the power accounted for."""
    s = load_scene("default")
    ln = s.lens
    z_top = float(ln.top_z(0.0))
    cases = [((40.0, 0.0, 0.0), (-0.6, 0.0, 0.8)),  # meridian plane (the paper's case 1)
             ((0.0, 0.0, -5.0), (0.0, 0.0, 1.0)),  # along the axis
             ((-30.0, 0.0, z_top), (1.0, 0.0, 0.0)),  # tangent to the top's apex
             ((50.0, 0.0, ln.centre_z), (-1.0, 0.0, 0.0)),  # straight at the side's widest point
             ((45.0, ln.centre_rho + ln.arc_radius, ln.centre_z), (-1.0, 0.0, 0.0)),  # grazing the side
             ((0.0, 0.0, 8.0), (0.3, 0.0, math.sqrt(1 - 0.09))),  # starting inside the lens
             ((40.0, 0.0, 0.0), (0.0, 0.0, -1.0)),  # away from the lens
             ((40.0, 0.0, 0.0), (0.0, 1.0, 0.0))]  # parallel to the LED plane
    O = np.array([c[0] for c in cases])
    D = np.array([c[1] for c in cases])
    for dt in ("float32", "float64"):
        r = engine.lens_rays(s.with_effects(add=["internal_bounces"]), O, D, dtype=dt)
        for key, v in r.items():
            assert np.isfinite(v).all(), (dt, key, v)
        assert ((r["power"] >= 0) & (r["power"] <= 1)).all()
        assert np.abs(r["power"] + r["reflected"] + r["absorbed"] - 1.0).max() < 1e-5
        assert set(r["code"]) <= {K.OUT, K.TIR_LOST, K.STOPPED, K.LOST, K.UNCONVERGED}
        assert r["power"][1] > 0.9 and np.allclose(r["direction"][1], [0, 0, 1])  # on axis: straight through
        assert r["power"][6] == 1 and np.allclose(r["direction"][6], [0, 0, -1])  # misses the lens
    # a source on the axis and a wide cone: the plano-sphere scene, all rays accounted for
    d = scene_to_dict(load_scene("plano-sphere"))
    d["leds"]["cone_half_angle_deg"] = 89.5
    r = trace_all(scene_from_dict(d), rays=20_000, sampler="random", engine="kernel")
    assert np.isfinite(r.E).all() and np.isfinite(r.V).all() and abs(r.traces[0].energy.residual) < 1e-6


def _cuda_sim_run(code: str) -> dict:
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", NUMBA_DISABLE_JIT="1", PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-W", "ignore", "-c", code], capture_output=True, text=True, env=env,
                       timeout=300, cwd=str(ROOT))
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


def test_cuda_kernel_logic_in_the_simulator():
    """The CUDA kernel (grid-stride loop, atomics, books) under numba's CUDA simulator agrees with the CPU kernel."""
    code = """
import json, numpy as np
from sim.optics import engine
from sim.optics.grid import ImageBins, PixelGrid
from sim.optics.multisource import led_azimuths
from sim.scene import load_scene
s = load_scene("default")
lay = ImageBins(PixelGrid((8, 8), (7.0, 7.0), s.plane.z), led_azimuths(s)[:3], vector=True).layout
(img,), tr = engine.trace_led(s, [lay], rays=900, sampler="grid", device="cuda")
print(json.dumps({"img": img.ravel().tolist(), "energy": tr.energy.as_dict(), "counters": tr.counters}))
"""
    sim = _cuda_sim_run(code)
    s = load_scene("default")
    lay = ImageBins(PixelGrid((8, 8), (7.0, 7.0), s.plane.z), led_azimuths(s)[:3], vector=True).layout
    (img,), tr = engine.trace_led(s, [lay], rays=900, sampler="grid")
    for key, v in tr.energy.as_dict().items():
        assert abs(v - sim["energy"][key]) < 1e-6, key
    assert sim["counters"] == tr.counters
    got = np.array(sim["img"])
    assert np.abs(got - img.ravel()).sum() < 1e-3 * np.abs(img).sum()


@pytest.mark.skipif(not engine.cuda_available()[0], reason="no CUDA device for numba.cuda")
def test_cuda_kernel_on_the_gpu_matches_the_cpu():
    s = load_scene("default")
    g = PixelGrid((32, 32), (2.0, 2.0), s.plane.z)
    a = trace_all(s, g, rays=200_000, engine="kernel")
    b = trace_all(s, g, rays=200_000, engine="kernel", device="cuda")
    assert abs(a.traces[0].energy.on_screen - b.traces[0].energy.on_screen) < 1e-6
    assert np.abs(a.E - b.E).sum() < 1e-3 * a.E.sum() and np.abs(a.V - b.V).sum() < 1e-3 * np.abs(a.V).sum()


def test_cuda_kernel_compiles_to_ptx(tracer_ptx):
    """The real numba-cuda compiler (libNVVM, no GPU, no driver) builds the tracer kernel with every
    device function (the simulator above compiles nothing). float32 here; ``iristac doctor``
    and ``tools/gpu_check.sh`` build both float types. The compile runs in a background process
    started when the suite is collected (``tests/conftest.py``: ``tracer_ptx``)."""
    status, ptx = tracer_ptx
    if status != "ok":
        pytest.skip(ptx)
    assert ".entry" in ptx and "atom.global.add.f32" in ptx
    assert ".f64" in ptx and ".f32" in ptx  # the float64 books beside float32 rays
