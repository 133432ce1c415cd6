"""The altered unit (calibration/altered_unit.py): its frames, imported through its own profile,
are the canonical frames again, but for the resampling and the colour gain it keeps."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.altered_unit import Alteration, alter_frames, load_profile_dict, make_altered_unit
from pipeline.base.errors import UserError


def _canonical(n: int = 3) -> np.ndarray:
    """Smooth DIGIT-size frames (640 x 480 portrait) with a distinct pattern per corner, so a
    wrong turn or crop shows."""
    y, x = np.mgrid[0:640, 0:480].astype(np.float64)
    frames = []
    for i in range(n):
        b = 60 + 80 * x / 480 + 10 * i
        g = 50 + 120 * y / 640
        r = 90 + 60 * np.exp(-((x - 120 - 40 * i) ** 2 + (y - 200) ** 2) / 4000.0)
        frames.append(np.stack([b, g, r], axis=-1))
    return np.clip(np.rint(np.stack(frames)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("rotate", [90, 180, 270])
def test_altered_frames_map_back_through_their_profile(rotate):
    frames = _canonical(2)
    alt = Alteration(size=(360, 480), rotate=rotate, border=(12, 8, 20, 4), gain=(0.85, 1.1, 0.92))
    stream, profile = alter_frames(frames, alt)
    assert stream.shape[1:3] != frames.shape[1:3]
    prof = load_profile_dict(profile)
    back = prof.fit_frames(stream).astype(np.float64)
    want = frames.astype(np.float64) * np.array(alt.gain)
    inner = (slice(None), slice(8, -8), slice(8, -8))  # resampling blurs the outermost pixels a little
    assert np.abs(back - want)[inner].mean() < 1.0 and np.abs(back - want)[inner].max() < 6
    # Without the gain undone the difference is the gain's: ~ 15 % of a 100 DN level.
    assert np.abs(back[..., 0] - frames[..., 0])[inner].mean() > 10


def test_make_altered_unit_writes_frames_and_a_profile_import_reads(tmp_path):
    from calibration.image_import import load_images

    frames = _canonical(3)
    frames[0] = frames[1]  # no press is needed: the import finds a reference among three frames
    unit = make_altered_unit(frames, tmp_path / "unit", seed=4)
    assert unit.alteration == Alteration.from_seed(4, (480, 640))
    assert sorted(p.name for p in unit.frames.iterdir()) == ["frame_0.png", "frame_1.png", "frame_2.png"]
    cap, report = load_images(unit.frames, profile=unit.profile, reference="frame_0")
    assert cap.frames.shape == (2, 1, 640, 480, 3) and report["mm_per_px"] == pytest.approx(0.0266)
    assert cap.meta["sensor_profile"] == "digit-altered-4" and cap.meta["calibration_drift"] == "field"
    # A folder of the canonical frames gives the same copy as the array.
    import cv2

    (tmp_path / "canonical").mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / "canonical" / f"frame_{i}.png"), f)
    again = make_altered_unit(tmp_path / "canonical", tmp_path / "again", seed=4)
    cap2, _ = load_images(again.frames, profile=again.profile, reference="frame_0")
    np.testing.assert_array_equal(cap2.frames, cap.frames)


def test_bad_alterations_are_one_line():
    with pytest.raises(UserError, match="rotate must be 0, 90, 180 or 270"):
        Alteration((360, 480), rotate=45)
    with pytest.raises(UserError, match="640 x 480 px"):
        alter_frames(np.zeros((1, 480, 640, 3), np.uint8), Alteration((360, 480)))
