"""The virtual sensor's calibration is keyed by its rendering's parameters (the calibrate stage's
``render`` source): the result equals the calibration of the same presses keyed by the rendered
capture's content, a cache hit renders nothing, and the key changes with everything the result
depends on."""

from __future__ import annotations

import numpy as np
import pytest

SHAPE, PITCH = (60, 80), 0.15


@pytest.fixture(scope="module")
def model():
    from sim.render import bare_ring_illumination

    return bare_ring_illumination(SHAPE, PITCH)


def test_parameter_key_same_result_as_content_key_and_hit_renders_nothing(model, tmp_path, monkeypatch):
    import sim.rendered_capture
    from pipeline.base.modes import load_mode
    from pipeline.base.store import StageStore
    from pipeline.live import virtual_calibration, virtual_calibration_key
    from pipeline.stages import calibrate as calibrate_stage
    from sim.contacts import contact_surfaces

    store = StageStore(tmp_path / "params")
    cal = virtual_calibration(store, model, "bare", "trichromatic", "lut")
    # The same presses rendered and calibrated as before this keying: by the capture's content.
    presses = contact_surfaces("sphere", SHAPE, PITCH, 8, size_mm=2.0, depth_mm=0.6, spread_mm=0.3 * min(SHAPE) * PITCH,
                               seed=11)
    cap = sim.rendered_capture.render_capture(model, load_mode("trichromatic"), presses, noise_dn=1.0, bit_depth=8,
                                              seed=11)
    ref, _, _ = calibrate_stage.run(StageStore(tmp_path / "content"), cap, ball_radius_mm=2.0, models=["lut"])
    assert sorted(cal.data) == sorted(ref.data)
    for name in ref.data:
        np.testing.assert_array_equal(cal.data[name], ref.data[name], err_msg=name)

    def no_render(*args, **kwargs):
        raise AssertionError("a cached virtual calibration was rendered again")

    monkeypatch.setattr(sim.rendered_capture, "render_capture", no_render)
    again = virtual_calibration(store, model, "bare", "trichromatic", "lut")
    key = virtual_calibration_key(store, model, "bare", "trichromatic", "lut")
    assert again.provenance["iristac_key"] == key.digest and store.path_for(key).is_file()
    for name in ref.data:
        np.testing.assert_array_equal(again.data[name], ref.data[name], err_msg=name)


def test_key_changes_with_everything_the_result_depends_on(model, tmp_path):
    from pipeline.base.store import StageStore
    from pipeline.live import virtual_calibration_key
    from sim.render import bare_ring_illumination

    store = StageStore(tmp_path)
    base = dict(model=model, ill_key="bare", mode="trichromatic", solver="lut")

    def key(**change):
        a = {**base, **change}
        return virtual_calibration_key(store, a.pop("model"), a.pop("ill_key"), a.pop("mode"), a.pop("solver"),
                                       **a).digest

    assert key() == key()
    variants = {"illumination": key(ill_key="other"), "pitch": key(model=bare_ring_illumination(SHAPE, 0.2)),
                "size": key(model=bare_ring_illumination((60, 90), PITCH)), "mode": key(mode="multicolour"),
                "models": key(solver="mlp"), "ball": key(ball_radius_mm=2.5), "presses": key(presses=7),
                "noise": key(noise_dn=2.0), "seed": key(seed=12)}
    assert key() not in variants.values()
    assert len(set(variants.values())) == len(variants), variants
