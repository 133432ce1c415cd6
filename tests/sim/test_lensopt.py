"""The lens optimizer's parts (sim/lensopt) and its entry point: design space, manufacturing limits,
objectives with common random numbers, the photometric-stereo condition numbers, the loss, the
searches, the tolerance analysis, the winner's scene file and the shipped paper scenes."""

import math

import numpy as np
import pytest
import torch

from pipeline.base.errors import UserError
from sim.lensopt.constraints import Manufacturing, closes, led_distance, lens_profile, violations
from sim.lensopt.objectives import Evaluator, Metrics, bare_limit, condition_numbers, loss
from sim.lensopt.search import Problem, run_search
from sim.lensopt.space import DEFAULT_BOUNDS, DesignSpace, apply_design, design_of
from sim.lensopt.tolerance import tolerance_table
from sim.scene import load_scene

torch.set_num_threads(1)

DEFAULT = load_scene("default-v1")
TINY = dict(rays=3000, grid=8)


def test_space_round_trips_linear_and_log_parameters():
    sp = DesignSpace(DEFAULT, {k: DEFAULT_BOUNDS[k] for k in ("arc_radius", "top_radius", "led_tilt_deg")})
    d = {"arc_radius": 13.5, "top_radius": 600.0, "led_tilt_deg": 12.0}
    assert sp.decode(sp.encode(d)) == pytest.approx(d)
    assert sp.decode([0.0, 1.0, 2.0])["top_radius"] == pytest.approx(1e5)  # clipped into the cube
    with pytest.raises(UserError, match="low < high"):
        DesignSpace(DEFAULT, {"apex_z": (5.0, 5.0)})
    with pytest.raises(UserError, match="unknown parameter"):
        apply_design(DEFAULT, {"no_such": 1.0})
    s = apply_design(DEFAULT, {"led_tilt_deg": 10.0, "top_conic": -2.0})
    assert s.leds.tilt_deg == 10.0 and s.lens.top_conic == -2.0 and design_of(s)["apex_z"] == 16.0


def test_closes_agrees_with_the_scene_loader():
    """The microsecond closure check used by the tolerance constraint says what load_scene says."""
    rng = np.random.default_rng(0)
    agree = 0
    for _ in range(300):
        d = {"arc_radius": rng.uniform(3, 40), "centre_rho": rng.uniform(0, 50), "centre_z": rng.uniform(-10, 25),
             "top_radius": float(np.exp(rng.uniform(np.log(20), np.log(1e5)))), "apex_z": rng.uniform(2, 26),
             "bottom_z": rng.uniform(0.3, 12), "top_conic": rng.choice([0.0, -2.0, 1.0])}
        try:
            apply_design(DEFAULT, d)
            loaded = True
        except UserError as exc:
            loaded = "inside" in str(exc)  # an LED inside a lens that closes: a layout error, not closure
        assert closes(**d) == loaded, d
        agree += loaded
    assert agree > 20


def test_profile_is_convex_and_led_distance_is_signed():
    prof = lens_profile(DEFAULT.lens, 100)
    a, b, c = prof, np.roll(prof, -1, 0), np.roll(prof, -2, 0)
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - b[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - b[:, 0])
    assert (cross >= -1e-9).all()  # counter-clockwise and convex
    dist = led_distance(DEFAULT)
    # LED (40, 0); the default lens's lower edge: bottom z = 3 at radius 39.5 -> about 3.04 mm.
    assert dist == pytest.approx(math.hypot(40.0 - DEFAULT.lens.bottom_rho, 3.0), abs=0.05)
    over = apply_design(DEFAULT, {"centre_rho": 45.0, "centre_z": 3.0, "arc_radius": 10.0, "bottom_z": 0.3,
                                  "apex_z": 12.0})
    assert 0 < led_distance(over) < 0.31  # the LED just under the bottom face
    v = violations(over, Manufacturing(led_clearance=0.5))
    assert v["led_clearance"] == pytest.approx(0.5 - led_distance(over))


def test_manufacturing_limits_measure_their_misses():
    thin = apply_design(DEFAULT, {"apex_z": 4.0, "bottom_z": 3.0, "top_radius": 1e5})
    v = violations(thin, Manufacturing(min_thickness=2.0, housing_radius=40.0))
    assert v["min_thickness"] == pytest.approx(1.0)
    widest = float(thin.lens.side_rho(thin.lens.rim_z))  # the arc widens upward up to the rim here
    assert v["housing_radius"] == pytest.approx(widest - 40.0, abs=1e-3) and widest > 40.0
    assert Manufacturing().resolved(DEFAULT).housing_radius == pytest.approx(45.0)  # ring + 5 > gel half-diagonal
    # A side arc that only just reaches the top: the lens would not survive a 0.1 mm error.
    fragile = apply_design(DEFAULT, {"arc_radius": 13.5, "centre_z": 10.0, "apex_z": 23.49, "top_radius": 1e5})
    assert violations(fragile, Manufacturing())["tolerance"] > 0
    assert violations(DEFAULT, Manufacturing())["tolerance"] == 0


def test_condition_numbers_closed_forms():
    V = np.zeros((3, 1, 2, 3))
    V[0, ..., 0] = V[1, ..., 1] = V[2, ..., 2] = 1.0
    V[2, 0, 1] = (0.0, 0.0, 0.0)  # pixel 1: the third light is dark -> rank 2
    drive = np.zeros((3, 3, 3))
    drive[[0, 1, 2], [0, 1, 2], :] = 1.0
    c = condition_numbers(V, drive)
    assert c[0, 0] == pytest.approx(1.0) and math.isinf(c[0, 1])
    V2 = V.copy()
    V2[0] *= 5.0  # one light five times brighter: singular values 5*sqrt3, sqrt3, sqrt3 (3 channels each)
    assert condition_numbers(V2, drive)[0, 0] == pytest.approx(5.0)
    # One frame, three channels from three LEDs (trichromatic): the same matrix.
    tri = np.zeros((1, 3, 3))
    tri[0, [0, 1, 2], [0, 1, 2]] = 1.0
    assert condition_numbers(V2, tri)[0, 0] == pytest.approx(5.0)


def test_loss_ranks_feasible_then_infeasible_then_untraced():
    good = Metrics(fraction_on_screen=0.4, uniformity_cv=0.2)
    bad = Metrics(fraction_on_screen=0.9, uniformity_cv=0.4)
    lim = {"max_cv": 0.25}
    lg, fg = loss(good, "flux", lim)
    lb, fb = loss(bad, "flux", lim)
    lu, fu = loss(None, "flux", lim, geometry_violation=0.2)
    assert fg and not fb and not fu
    assert lg == pytest.approx(-0.4) and lb == pytest.approx(-0.9 + 5.0 * 0.6)
    assert lg < lb < lu
    assert loss(good, "cv", {})[0] == pytest.approx(0.2)
    with pytest.raises(ValueError, match="needs valid_fraction"):
        loss(good, "valid", {})
    assert bare_limit("max_cv", good) == pytest.approx(0.198)


def test_evaluator_uses_common_random_numbers_and_agrees_with_trace_report():
    from sim.lens_design import trace_report

    ev = Evaluator(rays=20000, grid=10, modes=["trichromatic"], region=0.5)
    a, b = ev(DEFAULT), ev(DEFAULT)
    assert (a.fraction_on_screen, a.uniformity_cv, a.median_condition) == \
        (b.fraction_on_screen, b.uniformity_cv, b.median_condition)
    r = trace_report(DEFAULT, rays=20000, sampler="sobol")
    assert a.fraction_on_screen == pytest.approx(r["fraction_on_screen"], abs=1e-6)  # same rays, same screen
    bare = ev(DEFAULT.with_effects(remove=["lens"]))
    # The old default lens focuses each LED into a ring: worse conditioned and less uniform than bare.
    assert a.median_condition > 10 * bare.median_condition and a.uniformity_cv > 2 * bare.uniformity_cv
    assert bare.valid_fraction > 0.95


def test_searches_respect_the_budget_and_improve_on_the_start():
    ev = Evaluator(**TINY)
    space = DesignSpace(DEFAULT, {"apex_z": (10.0, 20.0), "bottom_z": (1.0, 5.0)})
    for method in ("cmaes", "random", "nelder-mead"):
        prob = Problem(space, ev, "flux", {}, Manufacturing())
        best, first, traj = run_search(prob, design_of(DEFAULT), method=method, evaluations=12, progress=False)
        assert len(traj.loss) == 12 == prob.count
        assert best.loss <= first.loss and best.feasible
        assert traj.best_value[-1] == pytest.approx(best.metrics.fraction_on_screen)
        assert all(s2 >= s1 for s1, s2 in zip(traj.seconds, traj.seconds[1:]))
    with pytest.raises(UserError, match="unknown method"):
        run_search(prob, design_of(DEFAULT), method="gradient", evaluations=3, progress=False)


def test_tolerance_table_moves_every_dimension_with_the_same_rays():
    tab = tolerance_table(DEFAULT, Evaluator(**TINY), names=["apex_z", "bottom_z", "led_tilt_deg"])
    assert [r["parameter"] for r in tab["rows"]] == ["apex_z", "bottom_z", "led_tilt_deg"]
    row = tab["rows"][0]
    assert row["minus_value"] == pytest.approx(15.9) and row["plus_value"] == pytest.approx(16.1)
    assert tab["worst_d_flux"] >= row["d_flux_max"] >= 0
    # A perturbation that leaves no lens is reported, not raised.
    edge = apply_design(DEFAULT, {"bottom_z": 3.0, "centre_z": 10.0, "arc_radius": 7.05})
    t2 = tolerance_table(edge, Evaluator(**TINY), names=["bottom_z"])
    assert t2["rows"][0]["minus"] is None and "minus: not a valid lens" in t2["rows"][0]["note"]
    assert t2["rows"][0]["plus"] is not None


def test_paper_scene_reproduces_the_papers_bare_fraction():
    from sim.lens_design import trace_report

    paper = load_scene("paper")
    r = trace_report(paper, rays=40000, sampler="sobol", no_lens=True)
    assert abs(r["fraction_on_screen"] - 0.635) < 0.01
    for name in ("paper", "paper-optimized", "default"):
        s = load_scene(name)
        assert not any(violations(s, Manufacturing()).values()), name


def test_optimize_lens_end_to_end_writes_a_traceable_winner(tmp_path):
    from sim.lens_design import OPTIMIZE_KEYS, optimize_lens

    r = optimize_lens("default-v1", objective="flux", modes=["trichromatic"], constraints={"max_cv": "bare"},
                      vary={"apex_z": (10.0, 20.0), "led_tilt_deg": (0.0, 30.0)}, evaluations=10, rays=4000, grid=8,
                      confirm_rays=20000, tolerance_rays=4000, out=tmp_path, progress=False, threads=1)
    assert set(OPTIMIZE_KEYS) <= set(r)
    assert r["evaluations"] == 10 and r["design"]["arc_radius"] == 13.5
    assert r["valid_fraction"] is not None and r["bare"]["valid_fraction"] is not None
    assert {row["parameter"] for row in r["tolerance"]["rows"]} == {"apex_z", "led_tilt_deg"}
    winner = load_scene(r["files"]["scene_file"])
    assert winner.lens.apex_z == pytest.approx(r["design"]["apex_z"], abs=1e-4)
    assert winner.leds.tilt_deg == pytest.approx(r["design"]["led_tilt_deg"], abs=1e-4)
    for k in ("plot", "trajectory", "section_start", "section_optimized"):
        assert (tmp_path / r["files"][k].split("/")[-1]).stat().st_size > 100
    with pytest.raises(UserError, match="needs lighting modes"):
        optimize_lens("paper", objective="valid", evaluations=2, progress=False)
    with pytest.raises(UserError, match="swept-arc"):
        optimize_lens("plano-sphere", evaluations=2, progress=False)
