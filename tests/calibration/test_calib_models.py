"""Every model recovers a synthetic truth; rank-deficient patterns are refused; CV is honest."""

import numpy as np
import pytest

from calibration.calibrate import calibrate
from calibration.models import FarFieldModel, LookupTable, MLPModel, NearFieldModel, TracedModel
from calibration.models.base import check_light_rank, solve_normals
from calibration.synthetic import synthetic_sphere_capture
from calibration.validate import cross_validate
from helpers import calibration_samples
from pipeline.base.errors import UserError
from pipeline.results.evaluate import angular_error_deg


@pytest.fixture(scope="module")
def point_far():
    return synthetic_sphere_capture((60, 80), 6, far_field=True, peak_dn=140, seed=3)


@pytest.fixture(scope="module")
def point_near():
    return synthetic_sphere_capture((60, 80), 6, peak_dn=140, seed=4)


def test_far_field_recovers_led_directions_and_gains(point_far):
    cap, tr = point_far
    s, r = calibration_samples(cap, tr)
    m = FarFieldModel()
    m.fit(s, r)
    L = m.lights[:, 0]  # white LEDs: channel 0 of each point pattern
    true = tr.V[:, 30, 40]
    ang = angular_error_deg(L / np.linalg.norm(L, axis=1, keepdims=True),
                            true / np.linalg.norm(true, axis=1, keepdims=True))
    assert ang.max() < 1.0
    for j in range(3):
        got = np.linalg.norm(m.lights[:, j], axis=1) / np.linalg.norm(true, axis=1)
        want = tr.gains[:, j]
        rel = (got / got.mean()) / (want / want.mean())
        assert np.abs(rel - 1).max() < 0.01


def test_traced_recovers_gains(point_near):
    cap, tr = point_near
    s, r = calibration_samples(cap, tr)
    m = TracedModel(tr.V, cap.drive)
    m.fit(s, r)
    want = tr.gains * tr.exposure / np.pi  # sigma absorbs exposure and 1/pi (albedo 1)
    assert np.abs(m.gains / want - 1).max() < 0.01


@pytest.mark.parametrize("name", ["near", "traced"])
def test_cross_validated_error_near_and_traced(point_near, name):
    cap, tr = point_near
    res = calibrate(cap, tr.ball_radius_mm, models=[name], illumination=tr.V, folds=3)
    assert res.reports[name]["cv"]["cv_mean_angular_error_deg"] <= 1.5


def test_light_field_layout_and_far_field_is_constant(point_near):
    cap, tr = point_near
    s, r = calibration_samples(cap, tr)
    far = FarFieldModel()
    far.fit(s, r)
    lf = far.light_field((60, 80))
    assert lf.shape == (6, 3, 60, 80, 3) and lf.dtype == np.float32
    assert np.ptp(lf, axis=(2, 3)).max() == 0
    tm = TracedModel(tr.V, cap.drive)
    tm.fit(s, r)
    lf = tm.light_field((60, 80))
    # The contract: I[p, :, :, c] ~ rho n . light_field[p, c]; on the flat reference n = z.
    pred = lf[..., 2].transpose(0, 2, 3, 1)
    assert np.abs(pred - r).mean() < 1.0


@pytest.fixture(scope="module")
def trichromatic():
    return synthetic_sphere_capture((60, 80), 10, mode="trichromatic", num_leds=12, peak_dn=140, far_field=True,
                                    seed=5)


def test_lut_recovers_truth_and_round_trips(trichromatic):
    cap, tr = trichromatic
    res = calibrate(cap, tr.ball_radius_mm, models=["lut"], folds=5)
    assert res.reports["lut"]["cv"]["cv_mean_angular_error_deg"] < 5.0
    lut = res.models["lut"].table
    again = LookupTable.from_arrays(lut.to_arrays())
    g1, v1 = lut.lookup(cap.frames[:2, 0].astype(float))
    g2, v2 = again.lookup(cap.frames[:2, 0].astype(float))
    assert g1.shape == (2, 60, 80, 2) and v1.dtype == bool
    np.testing.assert_array_equal(g1, g2)
    np.testing.assert_array_equal(v1, v2)
    assert np.isfinite(g1).all()


def test_mlp_recovers_truth_and_is_deterministic(trichromatic):
    cap, tr = trichromatic
    s, r = calibration_samples(cap, tr)
    a = MLPModel(epochs=150, max_samples=2000)
    b = MLPModel(epochs=150, max_samples=2000)
    a.fit(s, r)
    b.fit(s, r)
    na, _ = a.predict(s)
    nb, _ = b.predict(s)
    np.testing.assert_array_equal(na, nb)
    cv = cross_validate(lambda: MLPModel(epochs=150, max_samples=2000), s, r, folds=3)
    assert cv["cv_mean_angular_error_deg"] < 5.0
    g, ok = a.lookup(cap.frames[:1, 0])
    assert g.shape == (1, 60, 80, 2) and ok.all()


def test_rank_deficient_patterns_raise():
    # Only the two LEDs on one diameter of the ring: two light directions.
    cap, tr = synthetic_sphere_capture((60, 80), 4, num_leds=6, leds=[0, 3], peak_dn=140, seed=6)
    with pytest.raises(UserError, match="three independent light directions"):
        calibrate(cap, tr.ball_radius_mm, models="all", illumination=tr.V)


def test_rank_check_passes_full_ring(point_near):
    s, _ = calibration_samples(*point_near)
    assert check_light_rank(s) > 0.2


class _SpyNear(NearFieldModel):
    seen: list = []

    def fit(self, samples, reference=None):
        _SpyNear.seen.append(set(np.unique(samples.press).tolist()))
        return super().fit(samples, reference)


def test_cross_validation_never_fits_on_the_held_out_press(point_near):
    cap, tr = point_near
    s, r = calibration_samples(cap, tr)
    _SpyNear.seen = []
    cv = cross_validate(_SpyNear, s, r, folds=3)
    assert len(cv["folds"]) == 3 == len(_SpyNear.seen)
    for fold, seen in zip(cv["folds"], _SpyNear.seen):
        assert not set(fold["test_presses"]) & seen
        assert not set(fold["test_presses"]) & set(fold["train_presses"])
    assert sorted(p for f in cv["folds"] for p in f["test_presses"]) == sorted(cv["per_press"])


def test_solve_normals_float32_and_float64_agree():
    rng = np.random.default_rng(0)
    L = rng.normal(size=(50, 6, 3))
    L[..., 2] = np.abs(L[..., 2]) + 1
    n = rng.normal(size=(50, 3))
    n[:, 2] = np.abs(n[:, 2]) + 2
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    obs = np.einsum("nmk,nk->nm", L, n)
    lit = obs > 0
    n64, _, ok64 = solve_normals(np.where(lit, obs, 0.0), L)
    n32, _, ok32 = solve_normals(np.where(lit, obs, 0.0).astype(np.float32), L.astype(np.float32))
    fine = ok64 & ok32 & (lit.sum(1) >= 3)
    assert fine.mean() > 0.8
    assert angular_error_deg(n64[fine], n[fine]).max() < 1e-4
    assert angular_error_deg(n32[fine], n64[fine]).max() < 1e-2


def test_conv_learns_is_deterministic_and_predicts_frames_as_samples(trichromatic):
    """The network: two fits bit-identical; a whole frame gives each pixel what its samples give
    (valid convolutions, the frame's border repeated); stored and loaded it answers the same."""
    from calibration.models import ConvModel
    from calibration.samples import Samples

    cap, tr = trichromatic
    s, r = calibration_samples(cap, tr)
    train, test = s.subset(s.press < 7), s.subset((s.press >= 7) & s.contact)
    a, b = (ConvModel(width=8, dilations=(1, 2), epochs=100, tiles=64, batch=16, members=1) for _ in range(2))
    a.fit(train, r)
    b.fit(train, r)
    na, ok = a.predict(test)
    np.testing.assert_array_equal(na, b.predict(test)[0])
    assert ok.all() and angular_error_deg(na, test.normals).mean() < 6.0
    k = 8
    maps = a.normal_maps(test.images[k:k + 1], r)
    one = test.subset(test.press == k)
    np.testing.assert_allclose(maps.normals[0][one.rows, one.cols], a.predict(one)[0], atol=1e-5)
    _check_border_confidence(a, maps, one, radius_px=3)
    again = ConvModel.from_arrays(a.to_arrays())
    np.testing.assert_allclose(again.predict(test)[0], na, atol=1e-6)
    bare = Samples(test.intensities, test.reference, test.rows, test.cols, test.normals, test.press, test.contact,
                   test.shape)
    with pytest.raises(ValueError, match="whole frames"):
        a.predict(bare)


def _check_border_confidence(model, maps, samples, radius_px: int):
    """A network's confidence: 1 where its whole window lies inside the frame, falling toward
    the border (each axis: the share of ``2 radius_px + 1`` pixels inside), the same on the
    per-sample path."""
    conf = maps.confidence[0]
    h, w = conf.shape
    r = radius_px
    assert maps.mask[0].all() and np.all(conf[r:h - r, r:w - r] == 1.0)
    edge = (r + 1) / (2 * r + 1)
    np.testing.assert_allclose(conf[h // 2, [0, w - 1]], edge, rtol=1e-6)
    np.testing.assert_allclose(conf[[0, h - 1], w // 2], edge, rtol=1e-6)
    np.testing.assert_allclose(conf[0, 0], edge * edge, rtol=1e-6)
    assert np.all(np.diff(conf[h // 2, :r + 1]) > 0)
    assert "window" in maps.meta["confidence"]
    _, _, per_sample = model.predict_with_confidence(samples)
    np.testing.assert_allclose(per_sample, conf[samples.rows, samples.cols], rtol=1e-6)


def test_conv_lifts_a_weak_shading_for_training_and_stores_its_gain_in_the_first_layer(trichromatic):
    """A sensor whose presses change the colour three times less than another's (a soft gel's
    shading: every frame's change from the reference divided by 3), both lifted to one RMS for
    training, gets the network that answers its frames as the other's answers its own: the gain is
    three times larger and lives in the first layer, so the network takes the planes unscaled.
    Without the gain (``change_rms=None``) the two networks differ. Planes already above the floor
    are left alone: gain 1 and the very network of ``change_rms=None``."""
    import dataclasses

    from calibration.models import ConvModel

    cap, tr = trichromatic
    s, r = calibration_samples(cap, tr)
    weak = dataclasses.replace(s, images=r + (s.images - r) / np.float32(3.0),
                               intensities=s.reference + (s.intensities - s.reference) / np.float32(3.0))
    train, test = s.subset(s.press < 7), s.subset((s.press >= 7) & s.contact)
    weak_train, weak_test = weak.subset(weak.press < 7), weak.subset((weak.press >= 7) & weak.contact)
    opts = dict(width=8, dilations=(1, 2), epochs=60, tiles=48, batch=16, members=1)
    strong_fit, weak_fit = ConvModel(change_rms=1.0, **opts), ConvModel(change_rms=1.0, **opts)
    g_strong = strong_fit.fit(train, r)["change_gain"][0]
    g_weak = weak_fit.fit(weak_train, r)["change_gain"][0]
    assert g_strong > 1.0 and g_weak == pytest.approx(3.0 * g_strong, rel=1e-5)
    n_strong = strong_fit.predict(test)[0]
    np.testing.assert_allclose(weak_fit.predict(weak_test)[0], n_strong, atol=1e-3)  # rounding, through 60 steps
    again = ConvModel.from_arrays(weak_fit.to_arrays())  # the stored network: the gain is in its weights
    np.testing.assert_allclose(again.predict(weak_test)[0], weak_fit.predict(weak_test)[0], atol=1e-6)
    plain = ConvModel(change_rms=None, **opts)
    assert plain.fit(weak_train, r)["change_gain"] == [1.0]
    assert angular_error_deg(plain.predict(weak_test)[0], n_strong).mean() > 0.5
    above = ConvModel(change_rms=1e-3, **opts)  # a floor every press's change is above
    assert above.fit(weak_train, r)["change_gain"] == [1.0]
    np.testing.assert_array_equal(above.predict(weak_test)[0], plain.predict(weak_test)[0])
    with pytest.raises(ValueError, match="change_rms must be > 0 or None, got 0"):
        ConvModel(change_rms=0)


def test_conv_ensemble_averages_its_members_and_round_trips(trichromatic):
    """An ensemble of two networks (the default): its first member is the single network of the same
    seed, its answer the mean of its members' raw outputs, and stored and loaded it keeps both members."""
    from calibration.models import ConvModel

    cap, tr = trichromatic
    s, r = calibration_samples(cap, tr)
    train, test = s.subset(s.press < 7), s.subset((s.press >= 7) & s.contact)
    opts = dict(width=8, dilations=(1, 2), epochs=60, tiles=48, batch=16)
    pair, single, second = ConvModel(**opts), ConvModel(members=1, **opts), ConvModel(seed=1, members=1, **opts)
    for m in (pair, single, second):
        m.fit(train, r)
    assert len(pair.nets) == 2 and pair.net is pair.nets[0]
    img = test.images[8]
    window = (slice(10, 30), slice(5, 40))
    both = pair.predict_planes(img, r, *window)
    one, two = single.predict_planes(img, r, *window), second.predict_planes(img, r, *window)
    first, alone = pair.nets[0].state_dict(), single.net.state_dict()
    assert all(np.array_equal(first[k].numpy(), alone[k].numpy()) for k in alone)
    np.testing.assert_allclose(both, (one + two) / 2, atol=1e-5)
    assert np.abs(one - two).max() > 1e-3  # the members differ: the mean is not either one
    again = ConvModel.from_arrays(pair.to_arrays())
    assert again.members == 2 and len(again.nets) == 2
    np.testing.assert_allclose(again.predict(test)[0], pair.predict(test)[0], atol=1e-6)
    with pytest.raises(ValueError, match="members must be an integer >= 1, got 0"):
        ConvModel(members=0)
    from calibration.models import ConvFastModel

    assert (ConvModel().members, ConvFastModel().members) == (2, 1)  # the accurate network, the live one


def test_relative_change_is_blind_to_light_dimmed_alike_in_frame_and_reference():
    """A gain field common to a frame and its reference (vignetting, an LED's fall-off) scales the
    plain colour difference but leaves the relative change as it was (to the floor's share), and
    the relative change is its closed form ``2 (I - I_ref) / (I_ref + floor)``."""
    from calibration.models.conv import RELATIVE_FLOOR, feature_planes

    rng = np.random.default_rng(3)
    ref = rng.uniform(80.0, 200.0, (2, 6, 7, 3)).astype(np.float32)
    img = (ref * rng.uniform(0.7, 1.4, ref.shape)).astype(np.float32)
    gain = np.linspace(0.4, 1.0, 7, dtype=np.float32)[None, None, :, None]  # dimmer toward one side
    window = ((0, 6), (0, 7))
    for scale in (255.0, 1.0):
        rel = feature_planes(img, ref, *window, scale)[:6]
        want = 2.0 * (img - ref) / (ref + RELATIVE_FLOOR * scale)
        np.testing.assert_allclose(rel, want.transpose(0, 3, 1, 2).reshape(6, 6, 7), rtol=1e-5)
    # input_scale 1: a floor of 0.04 DN, nothing beside 80-200 DN
    rel, dimmed = (feature_planes(a, b, *window, 1.0)[:6] for a, b in ((img, ref), (img * gain, ref * gain)))
    np.testing.assert_allclose(dimmed, rel, rtol=1e-3, atol=1e-6)
    diff, ddim = (feature_planes(a, b, *window, 1.0, change="difference")[:6] for a, b in ((img, ref),
                                                                                          (img * gain, ref * gain)))
    np.testing.assert_allclose(ddim[..., 0], 0.4 * diff[..., 0], rtol=1e-4)
    with pytest.raises(ValueError, match="change must be one of"):
        feature_planes(img, ref, *window, 255.0, change="ratio")


def test_conv_stores_which_change_it_saw_and_older_networks_keep_the_difference(trichromatic):
    """``change`` travels with a stored network; arrays written before it existed (no ``change``)
    load as the difference they were trained on, and answer as before."""
    from calibration.models import ConvModel

    cap, tr = trichromatic
    s, r = calibration_samples(cap, tr)
    train, test = s.subset(s.press < 7), s.subset((s.press >= 7) & s.contact)
    opts = dict(width=4, dilations=(1,), epochs=20, tiles=16, batch=8, members=1)
    old, new = ConvModel(change="difference", **opts), ConvModel(**opts)
    for m in (old, new):
        m.fit(train, r)
    assert new.change == "relative" and ConvModel.from_arrays(new.to_arrays()).change == "relative"
    arrays = old.to_arrays()
    del arrays["change"]  # as stored before the relative change
    again = ConvModel.from_arrays(arrays)
    assert again.change == "difference"
    np.testing.assert_allclose(again.predict(test)[0], old.predict(test)[0], atol=1e-6)
    assert np.abs(new.predict(test)[0] - old.predict(test)[0]).max() > 1e-3
    with pytest.raises(ValueError, match="'change' must index"):
        ConvModel.from_arrays({**arrays, "change": np.asarray(5)})
    with pytest.raises(ValueError, match="change must be one of"):
        ConvModel(change="ratio")


def test_block_mean_and_upsampling_keep_a_ramp_in_place():
    """Shrinking by 2 then bringing back bilinearly returns a linear ramp exactly inside the
    frame (half a pixel off would shift it by 0.5 x the slope), and the block means sit on the
    block centres."""
    import torch

    from calibration.models.conv import block_mean, upsample_planes

    h, w = 12, 17  # odd width: the last block column is padded
    rows, cols = np.mgrid[:h, :w].astype(np.float32)
    ramp = (0.3 * rows - 0.7 * cols)[None, :, :, None]
    lo = block_mean(ramp, 2)
    assert lo.shape == (1, 6, 9, 1)
    np.testing.assert_allclose(lo[0, 2, 3, 0], 0.3 * 4.5 - 0.7 * 6.5, atol=1e-5)
    up = upsample_planes(torch.from_numpy(np.repeat(lo[..., 0][None], 2, axis=1)), 2, (h, w))[0, 0].numpy()
    assert up.shape == (h, w)
    np.testing.assert_allclose(up[1:-1, 1:-2], ramp[0, 1:-1, 1:-2, 0], atol=1e-4)


def test_conv_fast_matches_the_full_network_on_a_smooth_scene_and_round_trips(trichromatic):
    """The fast variant (the frame shrunk by 2): frames as samples, close to the full-resolution
    network on the smooth rendered presses, stored and loaded as itself."""
    from calibration.models import ConvFastModel, ConvModel

    cap, tr = trichromatic
    s, r = calibration_samples(cap, tr)
    train, test = s.subset(s.press < 7), s.subset((s.press >= 7) & s.contact)
    opts = dict(width=8, epochs=100, tiles=64, batch=16)
    fast, full = ConvFastModel(dilations=(1,), **opts), ConvModel(dilations=(1, 2), members=1, **opts)
    fast.fit(train, r)
    full.fit(train, r)
    nf, ok = fast.predict(test)
    ng = full.predict(test)[0]
    ef, eg = angular_error_deg(nf, test.normals).mean(), angular_error_deg(ng, test.normals).mean()
    assert ok.all() and ef < 4.0 and eg < 1.5 and angular_error_deg(nf, ng).mean() < 4.0
    k = 8
    maps = fast.normal_maps(test.images[k:k + 1], r)
    one = test.subset(test.press == k)
    np.testing.assert_allclose(maps.normals[0][one.rows, one.cols], fast.predict(one)[0], atol=1e-5)
    _check_border_confidence(fast, maps, one, radius_px=2)  # a radius of 1 on the frame shrunk by 2
    # as calibration.h5 holds it (models/conv-fast/...), read back as the fast variant
    from types import SimpleNamespace

    from calibration.stored import calibration_from_record

    rec = SimpleNamespace(path=None, meta={}, data={f"models/conv-fast/{k}": v for k, v in fast.to_arrays().items()})
    again = calibration_from_record(rec)[0]["conv-fast"]
    assert (type(again), again.name, again.downsample, again.dilations) == (ConvFastModel, "conv-fast", 2, (1,))
    np.testing.assert_allclose(again.predict(test)[0], nf, atol=1e-6)


def test_the_networks_window_is_sized_from_the_ball():
    """``calibrate`` gives the default network a frame shrunk to the ball's size in pixels
    (:func:`calibration.models.conv.ball_downsample`); the caller's ``downsample`` wins, and the
    live variant keeps its fixed factor (its cost is what it is for)."""
    from calibration.calibrate import model_factories

    cap, _ = synthetic_sphere_capture((40, 50), centers_rc=[(20.0, 25.0)], radii_px=[8.0], ball_radius_mm=1.5,
                                      num_leds=3)

    def made(name, ball_px, options=None):
        return model_factories([name], cap, None, 255.0, options, ball_px=ball_px)[name]()

    assert [made("conv", b).downsample for b in (16.0, 54.0, 78.0, 113.0)] == [1, 1, 2, 3]
    assert made("conv", 113.0, {"conv": {"downsample": 1}}).downsample == 1
    assert made("conv-fast", 113.0).downsample == 2 and made("conv", None).downsample == 1


def test_the_network_reports_the_balls_tilt_gain_but_does_not_apply_it(trichromatic):
    """Per-pixel models take the gain their held-out spheres ask for; the network
    (``applies_tilt_gain = False``) keeps 1, with the gain it would have had still reported."""
    cap, tr = trichromatic
    res = calibrate(cap, tr.ball_radius_mm, models=["near", "conv"], folds=2,
                    model_options={"conv": {"width": 8, "dilations": (1, 2), "epochs": 60, "tiles": 64,
                                            "batch": 16, "members": 1}})
    near, conv = res.reports["near"]["cv"], res.reports["conv"]["cv"]
    assert near["tilt_gain_source"] in ("ball", "regression") and res.models["near"].tilt_gain == near["tilt_gain"]
    assert near["tilt_gain"] != 1.0
    assert conv["tilt_gain_source"] == "none" and conv["tilt_gain"] == 1.0 and res.models["conv"].tilt_gain == 1.0
    assert conv["regression_tilt_gain"] != 1.0 and conv["ball_gain"]["attempted"] > 0
    assert res.models["conv"].max_tilt is not None  # the tilt clip still applies
    # What calibrate prints about the best model's spheres says whether their gain was applied.
    from calibration.calibrate import _ball_summary

    assert _ball_summary("conv", res.reports)["applied"] is False
    assert _ball_summary("near", res.reports)["applied"] is (near["tilt_gain_source"] == "ball")
