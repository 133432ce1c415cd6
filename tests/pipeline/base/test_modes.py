"""Lighting-mode files: they validate, and the drive matrices are what the files say."""

import math

import numpy as np
import pytest
import yaml

from pipeline.base.errors import UserError
from pipeline.base.modes import (
    MODES_DIR,
    LightingMode,
    ModeFrame,
    list_modes,
    load_mode,
    mode_brightness,
    mode_drive,
    save_mode,
)

BUILTIN = ["monochromatic", "multicolour", "point", "trichromatic"]


def test_builtin_modes_are_listed_and_validate():
    assert set(BUILTIN) <= set(list_modes())
    for name in list_modes():
        mode = load_mode(name)
        assert mode.name == name and mode.num_leds == 24
        d = mode_drive(mode)
        assert d.dtype == np.float32 and d.shape == (len(mode.frames), 24, 3)
        assert d.min() >= 0 and d.max() <= 1


@pytest.mark.parametrize("name", BUILTIN)
def test_drive_matrices_are_what_the_files_say(name):
    raw = yaml.safe_load((MODES_DIR / f"{name}.yaml").read_text())
    mode = load_mode(name)
    assert [f.name for f in mode.frames] == [f["name"] for f in raw["frames"]]
    for f, rf in zip(mode.frames, raw["frames"]):
        np.testing.assert_array_equal(f.drive, np.array(rf["drive"], dtype=float))
        assert f.brightness == rf.get("brightness", 1.0)
    expected = np.stack([np.array(f["drive"]) for f in raw["frames"]]).astype(np.float32)  # the capture layout's dtype
    np.testing.assert_array_equal(mode_drive(name), expected)


def test_modes_are_the_paper_fig5_patterns():
    point = mode_drive("point")
    np.testing.assert_array_equal(point, np.repeat(np.eye(24)[:, :, None], 3, axis=2))
    mono = mode_drive("monochromatic")
    tri = mode_drive("trichromatic")[0]
    assert mono.shape == (3, 24, 3)
    for s in range(3):
        lit = np.zeros(24, bool)
        lit[8 * s:8 * s + 8] = True
        assert np.all(mono[s][lit] == 1) and np.all(mono[s][~lit] == 0)
        assert np.all(tri[lit, s] == 1) and np.all(np.delete(tri[lit], s, axis=1) == 0)  # sector s -> colour s
    wheel = mode_drive("multicolour")[0]
    phi = np.radians(15 * np.arange(24))
    centres = np.radians([52.5, 172.5, 292.5])
    np.testing.assert_allclose(wheel, 0.5 * (1 + np.cos(phi[:, None] - centres)), atol=5e-7)
    # each channel's equivalent source sits at its centre, pulled toward the axis (the paper's point):
    # half the ring radius for the cos wheel, against sin(60)/(8 sin(7.5)) = 0.83 for an 8-LED sector
    for j in range(3):
        eq = (wheel[:, j] * np.exp(1j * phi)).sum() / wheel[:, j].sum()
        eq_tri = (tri[:, j] * np.exp(1j * phi)).sum() / tri[:, j].sum()
        assert (np.angle(eq) - centres[j] + np.pi) % (2 * np.pi) - np.pi == pytest.approx(0, abs=1e-6)
        assert abs(eq) == pytest.approx(0.5, abs=1e-6)
        assert abs(eq_tri) == pytest.approx(math.sin(math.pi / 3) / (8 * math.sin(math.pi / 24)), abs=1e-6)


def test_user_mode_file_roundtrip(tmp_path):
    d = np.zeros((24, 3))
    d[[0, 6, 12, 18]] = [0.25, 0.5, 1.0]
    mode = LightingMode("cross", [ModeFrame("a", d, 0.5), ModeFrame("b", d[::-1].copy(), 1.0)], "four LEDs")
    p = save_mode(mode, tmp_path / "cross.yaml")
    back = load_mode(p)
    assert back.name == "cross" and back.description == "four LEDs" and back.pattern_names == ["a", "b"]
    np.testing.assert_array_equal(mode_drive(back), mode_drive(mode))
    np.testing.assert_array_equal(mode_brightness(p), [0.5, 1.0])


def _write(tmp_path, obj, name="bad.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(obj))
    return p


@pytest.mark.parametrize("mutate,match", [
    (lambda m: m.pop("leds"), "leds"),
    (lambda m: m.update(colour=1), "colour"),
    (lambda m: m["frames"][1]["drive"][3].__setitem__(0, 1.5), r"frames/1/drive/3/0"),
    (lambda m: m["frames"][0]["drive"].pop(), r"frames/0/drive: expected 24 rows"),
    (lambda m: m["frames"][1].__setitem__("brightness", -1), r"frames/1/brightness"),
    (lambda m: m["frames"][1].__setitem__("name", "f0"), r"frames/1/name: duplicate"),
])
def test_bad_mode_files_name_the_file_and_key(tmp_path, mutate, match):
    good = {"name": "x", "leds": 24,
            "frames": [{"name": f"f{k}", "brightness": 1.0, "drive": [[0.0, 0.0, 0.0] for _ in range(24)]} for k in range(2)]}
    good = yaml.safe_load(yaml.safe_dump(good))  # fresh nested lists
    load_mode(_write(tmp_path, good, "good.yaml"))
    mutate(good)
    p = _write(tmp_path, good)
    with pytest.raises(UserError, match=match) as info:
        load_mode(p)
    assert "bad.yaml" in str(info.value)


def test_unknown_mode_name_lists_the_known_ones():
    with pytest.raises(UserError, match="unknown lighting mode 'disco'.*multicolour"):
        load_mode("disco")
