"""Stage 2, synthesize: the illumination model, its light matrices and the store round trip."""

import numpy as np
import pytest
import torch

from pipeline.base.errors import UserError
from pipeline.base.store import StageStore, StoreError
from pipeline.stages.synthesize import run as run_synthesize
from sim.illumination_model import IlluminationModel, light_matrices
from sim.scene import load_scene
from sim.synthesize import default_illumination, load_illumination, save_illumination, synthesize

# Two cores shared by several test runs: a second intra-op thread mostly waits on barriers
# (measured 4-10x slower per op under that load), so the tracer tests run single-threaded.
torch.set_num_threads(1)


def _drive(L=24, P=3):
    rng = np.random.default_rng(0)
    return rng.random((P, L, 3))


def test_synthesize_model_and_light_matrices():
    drive, bright, gains = _drive(), np.array([1.0, 0.5, 2.0]), np.linspace(0.5, 1.5, 24)
    m = synthesize("default", (12, 16), 2.0, rays=20_000, drive=drive, brightness=bright, gains=gains, exposure=3.0)
    assert isinstance(m, IlluminationModel) and m.V.shape == (24, 12, 16, 3) and m.V.dtype == np.float32
    assert np.isfinite(m.V).all() and m.gel_z == load_scene("default").plane.z
    # LEDs are on the camera side of the gel: light arrives from +z (reconstruction frame).
    assert (m.V[..., 2] >= 0).all() and m.V[..., 2].sum() > 0
    lm = m.meta["light_matrices"]
    assert lm.shape == (3, 3, 12, 16, 3)
    assert np.allclose(lm, light_matrices(m.V, drive, bright, 3.0, gains), rtol=1e-4, atol=1e-6 * np.abs(lm).max())
    # LED 6 sits on +y (optical), i.e. toward smaller y in the reconstruction frame... and its
    # field points back toward it: at the image centre V has a -y (recon) component.
    cy, cx = 6, 8
    assert m.V[6, cy, cx, 1] < 0 and m.V[0, cy, cx, 0] > 0


def test_store_round_trip_and_cache(tmp_path):
    store = StageStore(tmp_path / "cache")
    drive = _drive(P=2)
    scene = load_scene("default").with_effects(add=["depth_field"])
    a = run_synthesize(store, scene, (8, 10), 3.0, rays=10_000, drive=drive)[0]
    files = list((tmp_path / "cache").rglob("*.h5"))
    assert len(files) == 1
    mtime = files[0].stat().st_mtime_ns
    b = run_synthesize(store, scene, (8, 10), 3.0, rays=10_000, drive=drive)[0]
    assert files[0].stat().st_mtime_ns == mtime  # read back, not recomputed
    assert np.array_equal(a.V, b.V) and np.array_equal(a.V_depth, b.V_depth)
    c = load_illumination(files[0])
    assert np.array_equal(c.V, a.V) and np.array_equal(c.meta["light_matrices"], a.meta["light_matrices"])
    assert c.V_depth.shape == (len(c.depth_heights), 24, 8, 10, 3) and 0.0 in c.depth_heights.tolist()
    assert np.allclose(c.led_positions, load_scene("default").leds.geometry()[0], atol=1e-5)
    # The field changes with gel height (depth-dependent light field).
    assert not np.allclose(c.V_depth[0], c.V_depth[-1])
    # A different parameter is a different entry.
    run_synthesize(store, scene, (8, 10), 3.0, rays=12_000, drive=drive)
    assert len(list((tmp_path / "cache").rglob("*.h5"))) == 2
    # Standalone file written and read back.
    out = save_illumination(a, tmp_path / "illumination.h5")
    d = load_illumination(out)
    assert np.array_equal(d.V, a.V) and d.mm_per_px == 3.0
    # A corrupt file is a clear error naming the file.
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not an hdf5 file")
    with pytest.raises(StoreError, match="bad.h5"):
        load_illumination(bad)


def test_dispersion_gives_per_channel_fields():
    scene = load_scene("default").with_effects(add=["dispersion"])
    m = synthesize(scene, (6, 8), 4.0, rays=10_000, drive=_drive(P=1))
    vc = m.meta["V_channels"]
    assert vc.shape == (3, 24, 6, 8, 3)
    assert np.allclose(vc.mean(0), m.V, atol=1e-9) and not np.allclose(vc[0], vc[2])


def test_bad_inputs_are_user_errors():
    with pytest.raises(UserError, match=r"drive must have shape \(P, 24, 3\), got \(2, 5, 3\)"):
        synthesize("default", (4, 4), 1.0, rays=100, drive=np.zeros((2, 5, 3)))
    with pytest.raises(UserError, match="mm_per_px"):
        synthesize("default", (4, 4), -1.0, rays=100)
    with pytest.raises(UserError, match="shape"):
        synthesize("default", (0, 4), 1.0, rays=100)


def test_default_illumination_is_quick_and_sane():
    m = default_illumination((30, 40), 1.0, rays=50_000)
    assert m.V.shape == (24, 30, 40, 3) and np.isfinite(m.V).all()
    assert m.meta["method"] == "hits" and m.meta["energy_residual"] < 1e-5
