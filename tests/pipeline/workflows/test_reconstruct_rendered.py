"""reconstruct() on captures from the project's renderer (sim.rendered_capture), and the
lookup-table solver with the calibration stage's own LookupTable."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.base.frames import normals_to_gradients
from pipeline.base.store import Record
from pipeline.workflows.reconstruct import reconstruct
from sim.render import bare_ring_illumination
from sim.rendered_capture import render_capture, sphere_presses
from support_recon import _one_torch_thread  # noqa: F401

SHAPE, MM = (30, 40), 0.15


@pytest.fixture(scope="module")
def model():
    return bare_ring_illumination(SHAPE, MM)


def _illumination_record(model):
    return Record("illumination", {"V": np.asarray(model.V, np.float32),
                                   "led_positions": np.asarray(model.led_positions, np.float64)},
                  {"mm_per_px": model.mm_per_px, "gel_z": float(model.gel_z)})


def test_rendered_monochromatic_capture_nearfield_beats_farfield(model, tmp_path):
    presses = sphere_presses(SHAPE, MM, 2.0, [0.3, 0.4], centers=[(0.0, 0.0), (0.5, -0.3)])
    cap = render_capture(model, "monochromatic", presses, noise_dn=1.0, seed=3)
    ill = _illumination_record(model)
    near = reconstruct(cap, illumination=ill, solver="nearfield", integrator="dst", store=tmp_path)
    far = reconstruct(cap, illumination=ill, solver="lstsq", integrator="dst", store=tmp_path)
    assert near.summary["valid_fraction"] == 1.0
    assert near.summary["normal_mean_error_deg"] < 1.0
    assert near.summary["depth_rmse_mm"] < 0.02 * 0.35
    assert far.summary["normal_mean_error_deg"] > 2 * near.summary["normal_mean_error_deg"]


def test_lut_solver_with_the_calibration_lookup_table(model, tmp_path):
    LookupTable = pytest.importorskip("calibration.models.lut").LookupTable
    # Calibration: several presses of a 2 mm ball under the trichromatic pattern; the table
    # maps each pixel's colour change to the true gradient there.
    centers = [(-1.0, -0.6), (1.0, 0.6), (0.0, 0.0), (-1.0, 0.8), (1.0, -0.8)]
    cal = render_capture(model, "trichromatic", sphere_presses(SHAPE, MM, 2.0, [0.4] * 5, centers),
                         noise_dn=0.5, seed=1)
    dark = cal.data["dark"].astype(np.float64)
    ref = cal.data["reference"][0].astype(np.float64) - dark
    diff = (cal.data["frames"][:, 0].astype(np.float64) - dark - ref).reshape(-1, 3)
    p, q = normals_to_gradients(cal.data["truth/normals"].reshape(-1, 3))
    table, _ = LookupTable.build(diff, np.c_[p, q], ref, bins=24)
    calib = Record("calibration", {"circles": np.zeros((5, 8), np.float32),
                                   **{f"models/lut/{k}": v for k, v in table.to_arrays().items()}},
                   {"mm_per_px": MM, "ball_radius_mm": 2.0, "models": ["lut"]})
    test = render_capture(model, "trichromatic", sphere_presses(SHAPE, MM, 2.0, [0.35], [(0.3, 0.2)]),
                          noise_dn=0.5, seed=9)
    res = reconstruct(test, calibration=calib, solver="lut", integrator="dct", store=tmp_path)
    assert res.summary["valid_fraction"] > 0.9
    assert res.summary["normal_mean_error_deg"] < 3.0
    assert res.depth.data["height"][0].max() > 0.2
