"""Contact detection across sensors, drift removal, the built reference and the quality gate.

Cheap by design: small virtual sensors (exact truth) with every flaw a real sensor shows, a
handful of DIGIT frames (detection only), rendered presses for the gate. The full figures per
sensor (calibrate on some presses, judge on the others) are in ``iristac bench calibration
--sensors`` (docs/calibration.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.detect import DetectOptions, detect_contacts, detect_press, rim_inside
from calibration.gate import CalibrationRefused
from helpers import SHARED, run_cli
from pipeline.base.capture import Capture
from sim.virtual_sensor import CONTACT_LOOK_EFFECTS, SENSOR_EFFECTS, random_sensor, render_sensor

DIGIT = SHARED / "data" / "digit_ball_presses"
#: A real sensor's flaws, without the ones of the contact's own look (tested on their own below).
FLAWS = [e for e in SENSOR_EFFECTS if e not in CONTACT_LOOK_EFFECTS]


def _errors(circles, truth):
    acc = np.array([c.accepted for c in circles])
    c = np.array([x.center_xy for x in circles])
    r = np.array([x.radius_px for x in circles])
    centre = np.hypot(*(c - truth.center_xy).T)
    return acc, centre, r / truth.radius_px - 1.0


@pytest.mark.parametrize("seed, shape", [(1, (120, 160)), (3, (160, 120)), (5, (480, 640))])
def test_every_flaw_at_once_on_virtual_sensors(seed, shape):
    """Rim smoothing, markers, vignetting, optical blur, drift (gain, offset, field), column stripes, read
    noise and JPEG, portrait
    and landscape, 120 x 160 to 640 x 480: every press clear of the border, or cut by it with 55 % or
    more of its rim inside, is found, within 2 px (plus a quarter of the optical blur's sigma: 3.2 px
    at 640 x 480) and 15 % of its exact circle; a press refused lies over the border and its reason
    says so."""
    sensor = random_sensor(seed, shape=shape, num_presses=5, effects=FLAWS)
    assert sensor.effects == tuple(FLAWS)
    out = render_sensor(sensor)
    f, r = out.capture.linear()
    circles = detect_contacts(f, r, sensor.ball_radius_px)
    acc, centre, radius = _errors(circles, out.truth)
    rim = np.array([rim_inside(shape, c, rad) for c, rad in zip(out.truth.center_xy, out.truth.radius_px)])
    inside = ~np.asarray(out.truth.touches_border)
    assert (rim[~inside] < 1).all() and (rim[~inside] >= 0.55).any(), rim  # the draw holds a press cut by the border
    assert acc[inside | (rim >= 0.55)].all(), [c.reason for c in circles]
    assert centre[acc].max() < 2.0 + sensor.blur_px / 4 and -0.25 < radius[acc].min() and radius[acc].max() < 0.10, (centre, radius)
    for c, touches in zip(circles, out.truth.touches_border):
        if not c.accepted:
            assert touches and "border" in c.reason and "press further from the edge" in c.reason


def test_detection_scales_with_the_ball_up_to_1280x960():
    """The same presses at twice the size (1280 x 960) with twice the ball: the same circles, twice as large."""
    import cv2

    sensor = random_sensor(4, shape=(480, 640), num_presses=2, border_fraction=0.0, effects=FLAWS)
    out = render_sensor(sensor)
    f, r = out.capture.linear()
    small = detect_contacts(f, r, sensor.ball_radius_px)

    def up(a):
        return np.stack([cv2.resize(x, (1280, 960), interpolation=cv2.INTER_LINEAR) for x in a.reshape(-1, 480, 640, 3)]
                        ).reshape(a.shape[:-3] + (960, 1280, 3))

    big = detect_contacts(up(f), up(r), 2 * sensor.ball_radius_px)
    for a, b in zip(small, big):
        assert a.accepted and b.accepted
        np.testing.assert_allclose(np.array(b.center_xy), 2 * np.array(a.center_xy) + 0.5, atol=1.5)
        assert b.radius_px == pytest.approx(2 * a.radius_px, rel=0.05)


@pytest.mark.parametrize("look, seed", [("soft_shading", 1), ("marker_motion", 2)])
def test_contacts_found_by_their_shading_where_the_edges_mislead(look, seed):
    """A soft gel (its brightest change a highlight at one rim) and markers the presses move: the edge
    detector alone rejects most presses; calibrate's circles (each press filled where its own dots
    are, then every contact re-found as the cap that explains its colour change) are accepted and
    within 2 px of the truth."""
    from calibration.calibrate import find_circles
    from calibration.markers import detect_markers

    sensor = random_sensor(seed, shape=(120, 160), num_presses=10, border_fraction=0.0,
                           effects=["read_noise", "drift_gain", "drift_offset", look])
    out = render_sensor(sensor)
    cap = out.capture
    if look == "marker_motion":
        cap.markers = detect_markers(cap.reference)
    f, r = cap.linear()
    edges = detect_contacts(f, r, sensor.ball_radius_px)
    found = find_circles(cap, sensor.ball_radius_mm, strict=False)
    acc, centre, radius = _errors(found.circles, out.truth)
    edge_acc, edge_centre, _ = _errors(edges, out.truth)
    assert acc.sum() >= 9 and acc.sum() > edge_acc.sum() + 3, ([c.reason for c in edges], [c.reason for c in found.circles])
    assert np.median(centre[acc]) < 1.0 and centre[acc].max() < 2.0, centre
    assert -0.12 < np.median(radius[acc]) < 0.05, radius  # the edge detector's radii are 4-8 % small


def test_rim_inside_rule_accepts_contacts_near_the_border():
    """The fraction of a circle's rim inside the image against its closed form (a circle whose centre
    lies ``d`` inside an edge keeps ``1 - arccos(d / r) / pi`` of its rim), and the rule: at least half."""
    assert rim_inside((100, 100), (50.0, 50.0), 20.0) == 1.0
    assert rim_inside((100, 100), (88.0, 50.0), 12.0) == pytest.approx(1 - np.arccos(11 / 12) / np.pi, abs=0.01)
    assert rim_inside((100, 100), (5.0, 50.0), 12.0) == pytest.approx(1 - np.arccos(5 / 12) / np.pi, abs=0.01)
    assert rim_inside((100, 100), (0.0, 50.0), 12.0) == pytest.approx(0.5, abs=0.01)
    assert DetectOptions().min_rim_inside == 0.5


@pytest.mark.skipif(not DIGIT.is_dir(), reason=f"DIGIT frames not found at {DIGIT}")
def test_digit_presses_are_found():
    """Four of the DIGIT frames (640 x 480 portrait JPEG, column stripes, strong gradients): a round
    press, two cut in half by the dark line of the flat apex, one 2-3 px over the right border."""
    import cv2

    ref = cv2.imread(str(DIGIT / "frame_30.jpg"))[..., ::-1].astype(np.float32)[None]
    ball_px = 3.0 / 0.0266
    for k in (0, 6, 18, 28):
        f = cv2.imread(str(DIGIT / f"frame_{k}.jpg"))[..., ::-1].astype(np.float32)[None]
        c = detect_press(f, ref, ball_px)
        assert c.accepted, (k, c.reason)
        assert 0.35 * ball_px < c.radius_px < 0.7 * ball_px, (k, c.radius_px)
        # The disc holds the press: its mean difference is many times the background's.
        d = np.abs(f - ref - np.median(f - ref, axis=(1, 2), keepdims=True)).sum(axis=(0, 3))
        yy, xx = np.mgrid[:640, :480]
        dist = np.hypot(xx - c.center_xy[0], yy - c.center_xy[1])
        assert d[dist < 0.8 * c.radius_px].mean() > 3 * np.median(d), k
        assert d[dist < 0.3 * c.radius_px].mean() < d[(dist > 0.5 * c.radius_px) & (dist < c.radius_px)].mean()
        if k == 28:
            assert "of its rim inside the image" in c.reason


def test_drift_is_removed_before_detection():
    """A press 12 % brighter and 25 DN up against its reference: the same circle as without the drift;
    with drift removal off the detector is lost."""
    sensor = random_sensor(7, shape=(120, 160), num_presses=2, effects=["read_noise"], border_fraction=0.0)
    out = render_sensor(sensor)
    f, r = out.capture.linear()
    clean = detect_contacts(f, r, sensor.ball_radius_px)
    drifted = f * np.array([1.12, 0.9, 1.05]) + np.array([25.0, -20.0, 15.0])
    found = detect_contacts(drifted, r, sensor.ball_radius_px)
    for a, b in zip(clean, found):
        assert b.accepted and np.hypot(*np.subtract(a.center_xy, b.center_xy)) < 0.5
    lost = detect_contacts(drifted, r, sensor.ball_radius_px, DetectOptions(drift="none"))
    assert any(not c.accepted or np.hypot(*np.subtract(a.center_xy, c.center_xy)) > 3 for a, c in zip(clean, lost))


def test_a_reference_built_from_the_presses():
    """No clean frame: the reference built from the presses (contacts masked) is the true one up to a
    per-channel gain and offset (the presses' typical drift, which every press's own drift removal
    takes out again) within a few DN."""
    from calibration.reference import build_reference
    from pipeline.normals.drift import fit_drift

    sensor = random_sensor(2, shape=(120, 160), num_presses=10, effects=["read_noise", "drift_offset"],
                           border_fraction=0.0)
    out = render_sensor(sensor)
    f, r = out.capture.linear()
    built, rep = build_reference(f, sensor.ball_radius_px)
    assert rep["accepted"] == 10 and rep["uncovered_fraction"] == 0.0
    left = np.abs(fit_drift(built, r).remove(built) - r)
    assert np.median(left) < 1.5 and np.percentile(left, 99) < 6.0, (np.median(left), np.percentile(left, 99))


def test_built_reference_on_import(tmp_path):
    from calibration.image_import import load_images
    from sim.virtual_sensor import write_sensor_images

    sensor = random_sensor(2, shape=(120, 160), num_presses=8, effects=["read_noise"], border_fraction=0.0)
    res = write_sensor_images(tmp_path / "f", sensor)
    (tmp_path / "f" / res["reference"]).unlink()  # a folder with no clean frame
    cap, rep = load_images(tmp_path / "f", mm_per_px=sensor.mm_per_px, ball_radius_mm=sensor.ball_radius_mm)
    assert rep["reference"] == "built" and cap.frames.shape[0] == 8
    assert "built from the 8 presses" in cap.meta["reference_source"]
    with pytest.raises(Exception, match="no frame is clearly free of contact"):
        load_images(tmp_path / "f", mm_per_px=sensor.mm_per_px)


@pytest.mark.parametrize("seed", range(4))
def test_nanmedian_first_axis_equals_numpy(seed):
    """The built reference's median: numpy's nanmedian to the last bit, odd and even counts, columns
    with no valid value (NaN), float32 and float64."""
    import warnings

    from calibration.reference import nanmedian_first_axis

    rng = np.random.default_rng(seed)
    dtype = (np.float32, np.float64)[seed % 2]
    x = rng.normal(100, 5, (int(rng.integers(1, 12)), 7, 9, 3)).astype(dtype)
    x[rng.random(x.shape) < 0.3] = np.nan
    x[:, 0, 0] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        want = np.nanmedian(x, axis=0)
    got = nanmedian_first_axis(x)
    assert got.dtype == dtype and np.array_equal(got, want, equal_nan=True)
    with pytest.raises(ValueError, match=r"got \(0, 3\)"):
        nanmedian_first_axis(np.zeros((0, 3)))


def _gel_and_presses(k=12, seed=0):
    """A lit gel (1, 40, 60, 3) and ``k`` presses of it with read noise and a bright contact each."""
    rng = np.random.default_rng(seed)
    gel = rng.uniform(80, 160, (1, 40, 60, 3)).astype(np.float32)
    presses = gel + rng.normal(0, 2, (k, 1, 40, 60, 3)).astype(np.float32)
    yy, xx = np.mgrid[:40, :60]
    for i in range(k):
        presses[i, :, np.hypot(xx - 8 - 4 * i, yy - 15 - (i % 3) * 5) < 5] += 60.0
    return gel, presses


def test_a_built_reference_is_preferred_only_where_the_presses_match_it_better():
    """A no-contact frame taken under other light (a gain across the image, the DIGIT's case) loses
    to a reference built from other presses; the exact frame of the presses' light does not."""
    from calibration.reference import MIN_PRESSES_TO_COMPARE, PREFER_BUILT_RATIO, compare_with_built

    gel, presses = _gel_and_presses()
    stale = gel * np.linspace(0.9, 1.1, 60, dtype=np.float32)[None, None, :, None]
    moved = compare_with_built(presses, stale, 5.0)
    exact = compare_with_built(presses, gel, 5.0)
    assert moved["prefer_built"] and moved["ratio"] < 0.5 * PREFER_BUILT_RATIO, moved
    assert not exact["prefer_built"] and exact["ratio"] > 1.0, exact
    assert exact["presses_built"] + exact["presses_judged"] == len(presses)
    with pytest.raises(ValueError, match=f"K >= {MIN_PRESSES_TO_COMPARE}"):
        compare_with_built(presses[:MIN_PRESSES_TO_COMPARE - 1], gel, 5.0)
    with pytest.raises(ValueError, match=r"frame_reference must be \(1, 40, 60, 3\).*got \(40, 60, 3\)"):
        compare_with_built(presses, gel[0], 5.0)


def test_import_prefers_a_built_reference_to_a_noisy_frame_and_keeps_a_named_one(tmp_path):
    """``import images``: the found frame, as noisy as any one press, gives way to the median of the
    presses (and says why); named with ``--reference`` it is kept; without the ball radius nothing
    can be built and the found frame stays."""
    import cv2

    from calibration.image_import import load_images
    from sim.virtual_sensor import write_sensor_images

    sensor = random_sensor(4, shape=(120, 160), num_presses=12, effects=["read_noise"], border_fraction=0.0)
    res = write_sensor_images(tmp_path / "f", sensor)
    ref_file = tmp_path / "f" / res["reference"]
    kw = dict(mm_per_px=sensor.mm_per_px, ball_radius_mm=sensor.ball_radius_mm)
    cap, rep = load_images(tmp_path / "f", **kw)
    assert rep["reference"] == "built" and rep["reference_found"] == res["reference"], rep
    assert rep["reference_comparison"]["prefer_built"] and cap.frames.shape[0] == 12
    assert f"preferred to the no-contact frame {res['reference']}" in cap.meta["reference_source"]
    named, nrep = load_images(tmp_path / "f", reference=Path(res["reference"]).stem, **kw)
    assert nrep["reference"] == res["reference"] and nrep["reference_comparison"] is None
    assert np.array_equal(named.reference[0], cv2.imread(str(ref_file))[..., ::-1])
    _, plain = load_images(tmp_path / "f", mm_per_px=sensor.mm_per_px)
    assert plain["reference"] == res["reference"] and plain["reference_comparison"] is None


@pytest.fixture(scope="module")
def rendered():
    from calibration.synthetic import synthetic_sphere_capture

    return synthetic_sphere_capture((60, 80), 8, num_leds=3, drive=np.eye(3)[None], mm_per_px=0.1,
                                    ball_radius_mm=1.5, peak_dn=150, seed=3)


def test_too_few_presses_are_refused_and_force_writes(rendered, tmp_path):
    from pipeline.base.capture import write_capture

    cap, _ = rendered
    src = write_capture(tmp_path / "four.h5", cap.select(slice(0, 4)))
    out = tmp_path / "cal.h5"
    r = run_cli("calibrate", src, "--ball-radius", "1.5", "--model", "near", "--folds", "2", "--out", out,
                "--overlay", tmp_path / "o.png")
    assert r.returncode == 2 and not out.exists() and (tmp_path / "o.png").is_file()
    assert "calibration refused" in r.stderr and "too few presses" in r.stderr and "capture more presses" in r.stderr
    assert "light directions" not in r.stderr and "Traceback" not in r.stderr
    r = run_cli("calibrate", src, "--ball-radius", "1.5", "--model", "near", "--folds", "2", "--out", out, "--force",
                "--json")
    assert r.returncode == 0 and out.is_file()
    assert json.loads(r.stdout)["quality_gate"]["passed"] is False


def test_presses_without_contacts_are_refused_as_contacts_not_found(rendered):
    from calibration.calibrate import calibrate

    cap, _ = rendered
    noise = np.random.default_rng(0).normal(0, 1.0, (8,) + cap.reference.shape)
    blank = Capture(frames=np.clip(cap.reference[None] + noise, 0, 255).astype(np.uint8), reference=cap.reference,
                    drive=cap.drive, brightness=cap.brightness, mm_per_px=cap.mm_per_px, meta=dict(cap.meta))
    with pytest.raises(CalibrationRefused) as err:
        calibrate(blank, 1.5, models=["near"])
    v = err.value.verdict
    assert v.cause.startswith("contacts not found") and "too faint" in v.cause
    assert any("--overlay" in s for s in v.next_steps) and any("iristac label" in s for s in v.next_steps)
    assert err.value.circles is not None and len(err.value.circles) == 8


def test_misplaced_circles_are_not_blamed_on_the_lighting(rendered):
    """Circles 40 % of the ball off their contacts (a drifted reference did that to the old detector):
    whatever stops the calibration, it is not a lighting diagnosis."""
    from dataclasses import replace

    from calibration.calibrate import calibrate, find_circles

    cap, _ = rendered
    good = find_circles(cap, 1.5, strict=False).circles
    moved = [replace(c, center_xy=(c.center_xy[0] + 6.0, c.center_xy[1] - 4.0)) for c in good]
    try:
        res = calibrate(cap, 1.5, models=["near"], folds=4, circles=moved)
    except Exception as exc:  # noqa: BLE001 - any refusal, as long as it does not blame the lights
        assert "LEDs around the ring" not in str(exc), exc
    else:
        assert res.verdict is not None
        assert "lighting" not in res.verdict.cause


def test_eval_runs_on_labels_alone_when_nothing_is_detected(rendered):
    """A test capture whose presses the detector rejects (here: told every press is too faint) but that
    has hand labels: the labels judge, and the ball fit is reported."""
    from calibration.calibrate import calibrate
    from calibration.evaluate import evaluate_calibration, format_report
    from calibration.synthetic import synthetic_sphere_capture

    cap, _ = rendered
    res = calibrate(cap, 1.5, models=["near"], folds=4)
    test, ttr = synthetic_sphere_capture((60, 80), 2, num_leds=3, drive=np.eye(3)[None], mm_per_px=0.1,
                                         ball_radius_mm=1.5, peak_dn=150, seed=4)
    labelled = Capture(frames=test.frames, reference=test.reference, drive=test.drive, brightness=test.brightness,
                       mm_per_px=0.1, meta=dict(test.meta),
                       labels={"center_xy": ttr.centers_rc[:, ::-1].astype(np.float32),
                               "radius_px": ttr.radii_px.astype(np.float32)})
    ev = evaluate_calibration(res, labelled, 1.5, detect_options=DetectOptions(faint_snr=1e9))
    assert ev["accepted"] == 0 and ev["models"]["near"]["mean_deg"] is None
    assert ev["truth"]["labels"]["models"]["near"]["mean_deg"] is not None
    assert len(ev["ball_fit"]["near"]["per_press"]) == 2
    assert "no test press" in format_report(ev)


def test_label_truth_takes_a_virtual_sensors_exact_normals():
    """A capture that carries the gel's exact normals (a rim-smoothed virtual sensor) is judged on them:
    the contact samples' normals become the truth's, which leave the sphere cap near the rim."""
    import dataclasses

    from calibration.detect import Circle
    from calibration.evaluate import exact_normals
    from calibration.samples import collect_samples

    s = random_sensor(3, shape=(90, 120), num_presses=2, effects=["rim_smoothing"], border_fraction=0.0).replace(
        rim_smoothing_px=3.0)
    cap = render_sensor(s).capture
    f, r = cap.linear()
    circles = [Circle(tuple(c), float(a) * 1.05, float(a), 1.0, True, "") for c, a in
               zip(cap.truth["center_xy"], cap.truth["radius_px"])]
    samples = collect_samples(f, r, circles, s.ball_radius_mm, s.mm_per_px)
    n = exact_normals(cap, samples)
    m = samples.contact
    np.testing.assert_allclose(n[m], cap.truth["normals"][samples.press[m], samples.rows[m], samples.cols[m]],
                               atol=1e-6)
    rim = m & (samples.radial > 0.8)
    assert np.degrees(np.arccos(np.clip(np.sum(n[rim] * samples.normals[rim], 1), -1, 1))).max() > 1.0
    assert exact_normals(dataclasses.replace(cap, truth=None), samples) is None  # a real sensor's: none


def test_moved_blurred_dots_are_not_taken_for_noise():
    """Printed dots that a press moves, blurred by the optics, leave a ring in the difference image
    at every dot; a press's faintness is judged against the camera's noise measured away from its
    dots (each press's own), so the press keeps about the contrast it has without dots."""
    from scipy import ndimage

    from calibration.detect import detect_press
    from calibration.markers import press_markers
    from calibration.synthetic import synthetic_sphere_capture

    cap, _ = synthetic_sphere_capture((90, 120), centers_rc=[(45.0, 60.0)], radii_px=[9.0], ball_radius_mm=1.5,
                                      num_leds=3, noise_dn=4.0, peak_dn=120.0)
    f, r = cap.linear()
    clean = detect_press(f[0], r, 15.0)
    rows, cols = np.mgrid[0:90, 0:120]

    def dots(dy, dx):  # a blurred grid of dark dots every 10 px, shifted by (dy, dx)
        d = ((rows - 5 - dy) % 10 - 5) ** 2 + ((cols - 5 - dx) % 10 - 5) ** 2 <= 2
        return 1.0 - 0.6 * ndimage.gaussian_filter(d.astype(np.float64), 1.5) / 0.5

    ref_dots, press_dots = np.clip(dots(0, 0), 0.2, 1), np.clip(dots(1, 1), 0.2, 1)
    r_d, f_d = r * ref_dots[None, :, :, None], f[0] * press_dots[None, :, :, None]
    ref_mask = ref_dots < 0.7
    mask = press_markers(f_d[None], ref_mask)[0]
    found = detect_press(f_d, r_d, 15.0, exclude=mask)
    assert clean.accepted and found.accepted, found.reason
    assert found.snr > 0.5 * clean.snr, (found.snr, clean.snr)
    assert np.hypot(*(np.array(found.center_xy) - (60.0, 45.0))) < 1.5


def test_a_circle_far_from_the_press_strongest_change_is_not_its_contact():
    """A press mostly over the border leaves a bright sliver at the edge; a ring elsewhere (a dot
    the press moved) then wins the search for a disc. A circle that far from where the press
    changed the image most is not the press's contact: rejected, saying where the change is."""
    rng = np.random.default_rng(0)
    rows, cols = np.mgrid[0:120, 0:160]
    ref = np.full((1, 120, 160, 3), 100.0) + rng.normal(0, 1.0, (1, 120, 160, 3))
    f = ref.copy()
    ring = np.hypot(rows - 70, cols - 100)
    f[0][(ring > 5) & (ring < 8)] += 40.0
    f[0][np.hypot(rows - 40, cols + 12) < 14] += 120.0  # the press, all but 2 px over the left border
    f += rng.normal(0, 1.0, f.shape)
    c = detect_press(f.astype(np.float32), ref.astype(np.float32), 20.0)
    assert not c.accepted and "the strongest change (0, " in c.reason, c.reason
