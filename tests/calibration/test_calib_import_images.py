"""``iristac import images``: folders, templates and videos into capture.h5; bad input never writes a file."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from helpers import run_cli

_REPO = Path(__file__).resolve().parents[2]
DATA = next((p for p in (_REPO.parent / "shared" / "data" / "gelsight_ball_presses.npz",
                         _REPO.parent.parent / "shared" / "data" / "gelsight_ball_presses.npz") if p.is_file()),
            _REPO.parent / "shared" / "data" / "gelsight_ball_presses.npz")
needs_data = pytest.mark.skipif(not DATA.is_file(), reason=f"shared real frames not found at {DATA}")


def _write_rgb(path, rgb):
    """Write an RGB array with OpenCV (which expects BGR)."""
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def _colour_folder(tmp_path, dtype=np.uint16, presses=3):
    """A reference and presses whose colours are known: left third red, middle green, right blue."""
    top = 50000 if dtype == np.uint16 else 200
    folder = tmp_path / "shots"
    folder.mkdir()
    base = np.zeros((12, 18, 3), dtype)
    base[:, :6, 0] = top
    base[:, 6:12, 1] = top
    base[:, 12:, 2] = top
    _write_rgb(folder / "ref.png", base)
    for k in range(presses):
        img = base.copy()
        img[2 + k, 3 + 4 * k] = (top // 2, top // 3, top // 5)  # a "press": one odd pixel
        _write_rgb(folder / f"press_{k}.png", img)
    return folder, base


def test_16bit_png_keeps_depth_and_rgb_order(tmp_path):
    from pipeline.base.capture import read_capture

    folder, base = _colour_folder(tmp_path, np.uint16)
    out = tmp_path / "cap.h5"
    r = run_cli("import", "images", folder, "--out", out, "--mm-per-px", "0.05", "--reference", "ref", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["bit_depth"] == 16 and rep["dtype"] == "uint16" and rep["presses"] == 3 and not rep["reference_auto"]
    cap = read_capture(out)
    assert cap.frames.dtype == np.uint16 and cap.frames.shape == (3, 1, 12, 18, 3)
    np.testing.assert_array_equal(cap.reference[0], base)  # red stayed red: BGR -> RGB exactly once
    assert cap.reference[0, 0, 0].tolist() == [50000, 0, 0]
    assert cap.frames[1, 0, 3, 7].tolist() == [25000, 16666, 10000]
    assert cap.meta["bit_depth"] == 16 and cap.meta["frame_names"] == ["press_0.png", "press_1.png", "press_2.png"]


def test_jpeg_colours_and_automatic_reference(tmp_path):
    from calibration.importers import load_images

    folder = tmp_path / "jpg"
    folder.mkdir()
    rng = np.random.default_rng(0)
    gel = np.zeros((40, 60, 3), np.uint8)
    gel[..., 0], gel[..., 1], gel[..., 2] = 180, 90, 40  # an orange gel
    for k in range(5):
        img = gel.copy()
        if k != 3:  # frame 3 is the no-contact one; the others have a dark press in different places
            img[8:20, 4 + 12 * k: 14 + 12 * k] = (30, 150, 200)
        img = np.clip(img.astype(int) + rng.integers(-2, 3, img.shape), 0, 255).astype(np.uint8)
        _write_rgb(folder / f"f{k}.jpg", img)
    cap, rep = load_images(folder, mm_per_px=0.1)
    assert rep["reference"] == "f3.jpg" and rep["reference_auto"]
    assert rep["next_closest_distance"] > 5 * rep["reference_distance"]
    r, g, b = cap.reference[0].reshape(-1, 3).mean(0)
    assert r > 160 and 70 < g < 110 and b < 60  # still orange, not blue-ish (no BGR left over)


@needs_data
def test_real_frames_as_png_folder_equal_the_npz_import(tmp_path):
    """The shared frames written as PNGs (+ labels CSV) import to exactly the npz import's capture when
    the background is named, as the npz names it; found automatically, it gives way to a reference
    built from the 30 presses, which they match better (calibration.reference.compare_with_built)."""
    from calibration.importers import load_gelsight_npz, load_images
    from pipeline.base.capture import read_capture

    raw = np.load(DATA)
    folder = tmp_path / "real"
    folder.mkdir()
    assert cv2.imwrite(str(folder / "background.png"), raw["background"])  # the npz is BGR already
    rows = ["name,x,y,radius_px"]
    for k, (img, c, rad) in enumerate(zip(raw["images"], raw["touch_center_xy"], raw["touch_radius_px"])):
        assert cv2.imwrite(str(folder / f"press{k:02d}.png"), img)
        rows.append(f"press{k:02d},{c[0]},{c[1]},{rad}")
    (tmp_path / "labels.csv").write_text("\n".join(rows) + "\n")
    said: list[str] = []
    _, rep = load_images(folder, mm_per_px=0.1245, ball_radius_mm=2.0, log=said.append)
    assert rep["reference"] == "built" and rep["reference_found"] == "background.png", rep
    # The seconds-long step says so before it starts, and how to skip it.
    assert len(said) == 1 and "comparing the no-contact frame background.png" in said[0], said
    assert "--reference background skips this" in said[0]
    cmp = rep["reference_comparison"]
    assert cmp["built_residual_dn"] < 0.8 * cmp["frame_residual_dn"], cmp
    out = tmp_path / "cap.h5"
    r = run_cli("import", "images", folder, "--out", out, "--mm-per-px", "0.1245", "--ball-radius", "2",
                "--labels", tmp_path / "labels.csv", "--reference", "background")
    assert r.returncode == 0, r.stderr
    assert "reference 'background.png';" in r.stdout
    got, want = read_capture(out), load_gelsight_npz(DATA)
    np.testing.assert_array_equal(got.frames, want.frames)
    np.testing.assert_array_equal(got.reference, want.reference)
    np.testing.assert_array_equal(got.labels["center_xy"], want.labels["center_xy"])
    assert got.meta["ball_radius_mm"] == 2.0 and got.mm_per_px == pytest.approx(0.1245)


def test_pattern_template_point_mode(tmp_path):
    """A ring captured one LED at a time: files press{press}_led{pattern}.png, grey 8-bit."""
    from pipeline.base.capture import read_capture

    folder = tmp_path / "ring"
    folder.mkdir()
    for press in ["ref", "0", "1"]:
        for led in range(4):
            img = np.full((10, 14), 20 + 30 * led + (0 if press == "ref" else 5 * (int(press) + 1)), np.uint8)
            assert cv2.imwrite(str(folder / f"press{press}_led{led}.png"), img)
    (folder / "notes.txt").write_text("ignored")
    out = tmp_path / "cap.h5"
    r = run_cli("import", "images", folder, "--out", out, "--mm-per-px", "0.1", "--pattern",
                "press{press}_led{pattern}.png", "--reference", "ref", "--json")
    assert r.returncode == 0, r.stderr
    cap = read_capture(out)
    assert cap.frames.shape == (2, 4, 10, 14, 1) and cap.reference.shape == (4, 10, 14, 1)
    assert cap.meta["pattern_names"] == ["0", "1", "2", "3"] and cap.meta["frame_names"] == ["0", "1"]
    assert cap.reference[:, 0, 0, 0].tolist() == [20, 50, 80, 110]
    assert cap.frames[1, 2, 0, 0, 0] == 20 + 60 + 10
    assert cap.drive.shape == (4, 4, 3)


def test_video_frames(tmp_path):
    from calibration.importers import load_images

    path = tmp_path / "presses.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 10, (32, 24))
    if not w.isOpened():
        pytest.skip("this OpenCV build cannot write FFV1 video")
    for k in range(4):
        rgb = np.zeros((24, 32, 3), np.uint8)
        rgb[..., 0] = 200  # red gel
        if k:
            rgb[4:12, 8 * k - 6: 8 * k + 2] = (0, 0, 250)  # blue press
        w.write(np.ascontiguousarray(rgb[..., ::-1]))
    w.release()
    cap, rep = load_images(path, mm_per_px=0.2)
    assert rep["reference"] == "0" and cap.frames.shape == (3, 1, 24, 32, 3)
    assert cap.reference[0, 20, 20].tolist() == [200, 0, 0]
    assert cap.frames[2, 0, 8, 20].tolist() == [0, 0, 250]  # video frame 3: its press spans columns 18-25


def _bad(tmp_path, case):
    """Build one kind of bad input; returns (source, extra CLI args, the file the error must name)."""
    folder = tmp_path / "bad"
    folder.mkdir()
    img = np.full((8, 10, 3), 100, np.uint8)
    for k in range(3):
        _write_rgb(folder / f"f{k}.png", img)
    if case == "size":
        _write_rgb(folder / "f9.png", np.full((9, 10, 3), 100, np.uint8))
        return folder, [], "f9.png"
    if case == "unreadable":
        (folder / "f5.png").write_bytes(b"not a png at all")
        return folder, [], "f5.png"
    if case == "empty":
        empty = tmp_path / "empty"
        empty.mkdir()
        (empty / "readme.txt").write_text("no images here")
        return empty, [], "empty"
    if case == "template":
        return folder, ["--pattern", "press{press}_led{pattern}.png"], "press{press}_led{pattern}.png"
    if case == "depth":
        _write_rgb(folder / "f7.png", np.full((8, 10, 3), 1000, np.uint16))
        return folder, [], "f7.png"
    if case == "csv":
        (tmp_path / "labels.csv").write_text("name,x,y,radius_px\nf1,3,4,2\nf2,three,4,2\n")
        return folder, ["--labels", tmp_path / "labels.csv", "--reference", "f0"], "labels.csv:3"
    if case == "csv-name":
        (tmp_path / "labels.csv").write_text("f1,3,4,2\nf2,3,4,2\nf8,1,1,1\n")
        return folder, ["--labels", tmp_path / "labels.csv", "--reference", "f0"], "labels.csv:3"
    if case == "reference":
        return folder, ["--reference", "nope"], "nope"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["size", "unreadable", "empty", "template", "depth", "csv", "csv-name", "reference"])
def test_bad_input_is_one_line_error_and_writes_nothing(tmp_path, case):
    source, extra, named = _bad(tmp_path, case)
    out = tmp_path / "cap.h5"
    out.write_bytes(b"an existing file the failed import must not touch")
    r = run_cli("import", "images", source, "--out", out, "--mm-per-px", "0.1", *extra)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert named in r.stderr and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert out.read_bytes() == b"an existing file the failed import must not touch"
    assert not list(tmp_path.glob(".*.tmp.h5"))


def test_no_output_when_the_source_is_bad(tmp_path):
    source, extra, _ = _bad(tmp_path, "size")
    r = run_cli("import", "images", source, "--out", tmp_path / "new.h5", "--mm-per-px", "0.1", *extra)
    assert r.returncode == 2 and not (tmp_path / "new.h5").exists()


def test_markers_auto_on_import_and_a_bad_mask(tmp_path):
    """--markers auto stores the dark dots of the reference; a mask of the wrong size is one clear error."""
    from calibration.markers import draw_markers
    from pipeline.base.capture import read_capture

    folder = tmp_path / "dots"
    folder.mkdir()
    yy, xx = np.mgrid[:48, :64]
    gel = np.stack([120 + xx, 90 + yy, 140 - xx // 2], -1).astype(np.uint8)  # uneven light
    for k in range(4):
        img = gel.copy()
        if k:
            img[10:20, 8 + 14 * k: 16 + 14 * k] = (40, 160, 200)
        marked, truth = draw_markers(img, spacing_px=10.0, radius_px=1.5, offset_px=(5.0, 5.0))
        _write_rgb(folder / f"f{k}.png", marked)
    out = tmp_path / "cap.h5"
    r = run_cli("import", "images", folder, "--out", out, "--mm-per-px", "0.1", "--reference", "f0", "--markers",
                "auto", "--json")
    assert r.returncode == 0, r.stderr
    cap = read_capture(out)
    assert cap.markers is not None and cap.markers[truth].mean() > 0.95 and json.loads(r.stdout)["markers"] > 0
    bad = tmp_path / "mask.png"
    assert cv2.imwrite(str(bad), np.zeros((10, 10), np.uint8))
    r = run_cli("calibrate", out, "--ball-radius", "1", "--markers", bad, "--out", tmp_path / "cal.h5")
    assert r.returncode == 2 and "mask.png" in r.stderr and "10x10" in r.stderr and "Traceback" not in r.stderr


def test_float_tiff_keeps_float_values(tmp_path):
    from calibration.importers import load_images

    folder = tmp_path / "tif"
    folder.mkdir()
    base = np.zeros((6, 8, 3), np.float32)
    base[..., 0], base[..., 1], base[..., 2] = 0.25, 0.5, 0.75
    for k in range(3):
        img = base.copy()
        img[1, k] = (0.9, 0.1, 0.3)
        _write_rgb(folder / f"f{k}.tif", img)
    cap, rep = load_images(folder, mm_per_px=0.1, reference="f0")
    assert rep["bit_depth"] == 32 and cap.frames.dtype == np.float32
    assert cap.reference[0, 3, 3].tolist() == [0.25, 0.5, 0.75] and cap.frames[1, 0, 1, 2].tolist() == pytest.approx(
        [0.9, 0.1, 0.3])
