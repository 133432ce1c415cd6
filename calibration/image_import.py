"""Import a lab's own ball presses: a folder of images or a video -> ``capture.h5``.

``iristac import images SOURCE --out capture.h5`` (:func:`import_images`). SOURCE is

- a **folder** of JPEG/PNG/TIFF/BMP files (other files are ignored): one no-contact reference
  frame, every other frame one press; or, with a **name template** such as
  ``press{press}_led{pattern}.png``, one file per press and lighting pattern (a point-mode
  capture of an LED ring: P patterns per press);
- a **video** file (one frame per press, the reference among them; frames are named by
  their index ``0, 1, ...``).

The reference is the frame (or, with a template, the press) named by ``reference``; when
not given it is found automatically (:func:`auto_reference`): the frame closest to the
per-pixel median of all frames (which is the no-contact gel wherever the presses are spread
over the image), by the largest local difference. The choice, its distance and the next
closest frame's are reported. When no frame stands out (all are presses: the closest is not
:data:`CLEAN_RATIO` times closer than the next), or with ``reference="build"``, every frame is
a press and the reference is built from them (:mod:`calibration.reference`), which the
capture's ``reference_source`` attribute and every calibration report say. A frame found
automatically also gives way to a reference built from the presses when, given the ball
radius and enough presses, the presses match the built one clearly better
(:func:`calibration.reference.compare_with_built`: on the DIGIT folder the frame had been taken
under other light); naming the frame keeps it.

Pixel values are kept as the camera wrote them: a 16-bit PNG stays ``uint16`` (OpenCV's
``IMREAD_ANYDEPTH``), a float TIFF ``float32``; grey images have one channel. OpenCV
decodes colour as BGR: the channel axis is reversed exactly once, here, into the project's
RGB. Every frame must have the size, channel count and dtype of the first; any difference,
an unreadable file, an empty folder, a template that matches nothing or a bad label row is
one :class:`UserError` naming the file, raised before anything is written (and the write
itself is atomic), so an existing ``capture.h5`` is never touched by a failed import.

Optional: hand labels from a CSV (``name,x,y,radius_px``; x = column, y = row in pixels;
a header row is allowed), stored as ``labels/*`` (compared with, and fitted to by
``calibrate(..., circles="labels")``); a printed-marker mask (``markers="auto"`` detects dark dots in the reference,
or a mask image; :mod:`calibration.markers`), stored as ``markers (H, W)``.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.base.capture import Capture, write_capture
from pipeline.base.errors import UserError

__all__ = ["IMAGE_SUFFIXES", "VIDEO_SUFFIXES", "read_image", "read_video", "load_images", "import_images",
           "template_regex", "auto_reference", "read_labels_csv"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
_BIT_DEPTH = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16, np.dtype(np.float32): 32}


def read_image(path: str | Path) -> np.ndarray:
    """One image file as ``(H, W, C)`` RGB (C = 3) or grey (C = 1), at its own bit depth.

    Examples
    --------
    A 16-bit PNG written with known colours (OpenCV writes BGR) comes back RGB and 16-bit:

    >>> import cv2, tempfile, os
    >>> rgb = np.zeros((2, 3, 3), np.uint16); rgb[..., 0] = 40000; rgb[..., 2] = 7
    >>> p = os.path.join(tempfile.mkdtemp(), "x.png")
    >>> bool(cv2.imwrite(p, rgb[..., ::-1]))
    True
    >>> img = read_image(p)
    >>> img.dtype.name, img[0, 0].tolist()
    ('uint16', [40000, 0, 7])
    """
    import cv2

    path = Path(path)
    flags = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR  # keep 16-bit and float; alpha is dropped
    img = cv2.imread(str(path), flags)
    if img is None:
        raise UserError(f"{path}: not a readable image (OpenCV could not decode it)")
    if img.dtype == np.float64:
        img = img.astype(np.float32)
    if img.dtype not in _BIT_DEPTH:
        raise UserError(f"{path}: pixel type {img.dtype} is not supported (expected 8-bit, 16-bit or 32-bit float)")
    if img.ndim == 2:
        return img[..., None]
    if img.shape[2] == 4:  # pragma: no cover - ANYCOLOR already drops alpha; kept for other decoders
        img = img[..., :3]
    return np.ascontiguousarray(img[..., ::-1])  # OpenCV's BGR -> RGB, the one conversion


def read_video(path: str | Path) -> list[np.ndarray]:
    """Every frame of a video file, ``(H, W, 3)`` uint8 RGB."""
    import cv2

    path = Path(path)
    cap = cv2.VideoCapture(str(path))
    frames = []
    try:
        if not cap.isOpened():
            raise UserError(f"{path}: not a readable video (OpenCV could not open it)")
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(np.ascontiguousarray(frame[..., ::-1]) if frame.ndim == 3 else frame[..., None])
    finally:
        cap.release()
    if not frames:
        raise UserError(f"{path}: the video has no frames OpenCV could decode")
    return frames


def template_regex(template: str) -> re.Pattern:
    """A file-name template with ``{press}`` and ``{pattern}`` fields as a regular expression.

    Examples
    --------
    >>> m = template_regex("press{press}_led{pattern}.png").fullmatch("press07_led12.png")
    >>> m["press"], m["pattern"]
    ('07', '12')
    """
    fields = re.findall(r"\{(\w*)\}", template)
    if sorted(fields) != ["pattern", "press"]:
        raise UserError(f"--pattern {template!r}: the template needs exactly one {{press}} and one {{pattern}} field "
                        f"(got {', '.join('{' + f + '}' for f in fields) or 'none'})")
    parts = re.split(r"(\{press\}|\{pattern\})", template)
    rx = "".join(f"(?P<{p[1:-1]}>.+?)" if p in ("{press}", "{pattern}") else re.escape(p) for p in parts)
    return re.compile(rx)


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


#: The automatically found reference must be this much closer to the median frame than the next
#: closest frame to count as free of contact (measured: 0.24 on the DIGIT folder, 0.26 on the shared
#: GelSight frames; a folder of presses only: about 0.9); otherwise the reference is built from the presses.
CLEAN_RATIO = 0.5


def _built_reference(frames: np.ndarray, ball_radius_px: float, **kwargs) -> tuple[np.ndarray, dict[str, Any]]:
    """:func:`calibration.reference.build_reference` of every frame (keyword arguments passed on), in
    the frames' own dtype."""
    from calibration.reference import build_reference

    ref, report = build_reference(frames.astype(np.float32), ball_radius_px, **kwargs)
    if frames.dtype.kind in "ui":
        info = np.iinfo(frames.dtype)
        ref = np.clip(np.round(ref), info.min, info.max)
    return ref.astype(frames.dtype), report


def _prefer_built(presses: np.ndarray, frame: np.ndarray, ball_radius_px: float, name: str):
    """``(built, comparison)``: the reference built from ``presses`` (as :func:`_built_reference`, its
    note saying why) when they match it clearly better than the found no-contact ``frame``
    (:func:`calibration.reference.compare_with_built`), else ``(None, comparison)``; ``comparison`` is
    None with too few presses to compare."""
    from calibration.reference import MIN_PRESSES_TO_COMPARE, compare_with_built

    if len(presses) < MIN_PRESSES_TO_COMPARE:
        return None, None
    comparison = compare_with_built(presses, frame, ball_radius_px)
    if not comparison["prefer_built"]:
        return None, comparison
    why = (f", preferred to the no-contact frame {name}: presses it was not built from match it better (drift left "
           f"{comparison['built_residual_dn']:.2f} against {comparison['frame_residual_dn']:.2f} DN RMS; "
           f"--reference {Path(name).stem} keeps the frame)")
    return _built_reference(presses, ball_radius_px, why=why), comparison


def auto_reference(frames: np.ndarray, blur_px: float = 2.0) -> tuple[int, np.ndarray]:
    """Index of the frame closest to the per-pixel median of ``frames (N, P, H, W, C)``, and every distance.

    The distance is the largest *local* difference: ``|frame - median|`` summed over patterns
    and channels, blurred by ``blur_px`` (so noise and single hot pixels average out), its
    99.9th percentile over the image. A press changes a small disc a lot; drift of the lighting
    or JPEG noise change everything a little. A mean difference cannot tell these apart (on
    the shared real frames the background and the closest press tie at 13.0 mean), the local
    maximum can (29 for the background, at least 112 for any press).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> f = rng.normal(100, 3, (5, 1, 40, 60, 3))
    >>> for k, col in ((0, 2), (1, 14), (3, 26), (4, 38)):
    ...     f[k, :, 10:18, col:col + 8] += 60   # presses in different places; frame 2 has none
    >>> auto_reference(f)[0]
    2
    """
    from scipy import ndimage

    f = np.asarray(frames, np.float32)
    med = np.median(f, axis=0)
    diff = np.abs(f - med).sum(axis=(1, 4))  # (N, H, W)
    dist = np.array([np.percentile(ndimage.gaussian_filter(d, blur_px), 99.9) for d in diff])
    return int(np.argmin(dist)), dist


def read_labels_csv(path: str | Path, names: list[str]) -> dict[str, np.ndarray]:
    """Hand labels ``name,x,y,radius_px`` for the presses ``names`` (in that order).

    ``name`` may be a frame's file name or its stem (with a template: the press id). Every
    press needs exactly one row; ``name,,,`` (x, y and radius empty) marks a press a person
    rejected (the labeller writes those). Returns ``{"center_xy": (K, 2), "radius_px": (K,)}``
    float32 (NaN for rejected presses), plus ``"rejected": (K,)`` bool when any press is.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such labels file (expected CSV rows name,x,y,radius_px)")
    lookup = {}
    for i, n in enumerate(names):
        lookup[n] = i
        lookup.setdefault(Path(n).stem, i)
    rows: dict[int, tuple[float, float, float]] = {}
    try:
        with path.open(newline="") as fh:
            for line_no, row in enumerate(csv.reader(fh), start=1):
                if not row or all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
                    continue
                if line_no == 1 and row[0].strip().lower() == "name":
                    continue  # header
                if len(row) != 4:
                    raise UserError(f"{path}:{line_no}: expected 4 fields name,x,y,radius_px, got {len(row)}: {row}")
                name = row[0].strip()
                if all(not v.strip() for v in row[1:]):  # "name,,,": a press a person rejected
                    x = y = r = float("nan")
                else:
                    try:
                        x, y, r = (float(v) for v in row[1:])
                    except ValueError:
                        raise UserError(f"{path}:{line_no}: x, y and radius_px must be numbers (or all three empty: "
                                        f"rejected), got {row[1:]}") from None
                if not np.isnan(r) and not (np.isfinite([x, y, r]).all() and r > 0):
                    raise UserError(f"{path}:{line_no}: x and y must be finite and radius_px positive, got {row[1:]}")
                if name not in lookup:
                    raise UserError(f"{path}:{line_no}: no press named {name!r} (presses: "
                                    f"{', '.join(names[:5])}{' ...' if len(names) > 5 else ''})")
                k = lookup[name]
                if k in rows:
                    raise UserError(f"{path}:{line_no}: press {name!r} is labelled twice")
                rows[k] = (x, y, r)
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text CSV file") from None
    missing = [names[k] for k in range(len(names)) if k not in rows]
    if missing:
        raise UserError(f"{path}: no label for press(es) {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}"
                        f" (every press needs one row name,x,y,radius_px)")
    arr = np.array([rows[k] for k in range(len(names))], np.float32)
    out = {"center_xy": arr[:, :2], "radius_px": arr[:, 2]}
    if np.isnan(arr[:, 2]).any():
        out["rejected"] = np.isnan(arr[:, 2])
    return out


def _check_same(items: list[tuple[str, np.ndarray]]) -> None:
    first_name, first = items[0]
    for name, img in items[1:]:
        if img.shape[:2] != first.shape[:2]:
            raise UserError(f"{name}: image is {img.shape[1]}x{img.shape[0]} px but {first_name} is "
                            f"{first.shape[1]}x{first.shape[0]} px (every frame must have the same size)")
        if img.shape[2] != first.shape[2]:
            raise UserError(f"{name}: image has {img.shape[2]} channel(s) but {first_name} has {first.shape[2]}")
        if img.dtype != first.dtype:
            raise UserError(f"{name}: image is {_BIT_DEPTH[img.dtype]}-bit ({img.dtype}) but {first_name} is "
                            f"{_BIT_DEPTH[first.dtype]}-bit ({first.dtype}); mixed bit depths cannot share a capture")


def _folder_frames(folder: Path, template: str | None):
    """``(names, frames (N, P, H, W, C), pattern_names, paths)`` of a folder."""
    files = sorted((p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                    and p.suffix.lower() in IMAGE_SUFFIXES), key=lambda p: _natural_key(p.name))
    if not files:
        raise UserError(f"{folder}: no image files (expected {', '.join(IMAGE_SUFFIXES)})")
    if template is None:
        items = [(str(p), read_image(p)) for p in files]
        _check_same(items)
        return [p.name for p in files], np.stack([img for _, img in items])[:, None], ["all"]
    rx = template_regex(template)
    table: dict[str, dict[str, Path]] = {}
    for p in files:
        m = rx.fullmatch(p.name)
        if m:
            table.setdefault(m["press"], {})[m["pattern"]] = p
    if not table:
        raise UserError(f"{folder}: no file matches the template {template!r} (files look like {files[0].name})")
    patterns = sorted({pat for d in table.values() for pat in d}, key=_natural_key)
    presses = sorted(table, key=_natural_key)
    for press in presses:
        missing = [pat for pat in patterns if pat not in table[press]]
        if missing:
            want = template.replace("{press}", press).replace("{pattern}", missing[0])
            raise UserError(f"{folder / want}: missing (press {press!r} lacks pattern(s) {', '.join(missing)}; every "
                            f"press needs all {len(patterns)} patterns)")
    items = [(str(table[pr][pat]), read_image(table[pr][pat])) for pr in presses for pat in patterns]
    _check_same(items)
    frames = np.stack([img for _, img in items]).reshape(len(presses), len(patterns), *items[0][1].shape)
    return presses, frames, patterns


def _source_frames(src: Path, pattern: str | None):
    """``(names, frames (N, P, H, W, C), pattern_names, kind)`` of a folder of images or a video."""
    if src.is_dir():
        names, frames, pattern_names = _folder_frames(src, pattern)
        return names, frames, pattern_names, "images"
    if not src.is_file():
        raise UserError(f"{src}: no such folder or video file")
    if pattern is not None:
        raise UserError(f"{src}: --pattern applies to a folder of images, not to a file")
    if src.suffix.lower() in IMAGE_SUFFIXES:
        raise UserError(f"{src}: a single image is not a capture (give the folder holding the reference and the "
                        "presses, or a video)")
    vid = read_video(src)
    _check_same([(f"{src} frame {i}", f) for i, f in enumerate(vid)])
    return [str(i) for i in range(len(vid))], np.stack(vid)[:, None], ["all"], "video"


def _reference_index(src: Path, names: list[str], frames: np.ndarray, reference: str | None):
    """``(index, distances)`` of the no-contact frame: the one named, the one found automatically
    (:func:`auto_reference`), or ``None`` when it is to be built (``"build"``, or no frame stands
    out as untouched)."""
    if reference == "build":
        return None, None
    if reference is not None:
        matches = [i for i, n in enumerate(names) if reference in (n, Path(n).stem)]
        if not matches:
            raise UserError(f"{src}: no frame named {reference!r} for --reference (frames: "
                            f"{', '.join(names[:5])}{' ...' if len(names) > 5 else ''}, or 'build')")
        return matches[0], None
    ref_i, dist = auto_reference(frames)
    if len(dist) > 2 and dist[ref_i] > CLEAN_RATIO * np.sort(dist)[1]:
        return None, dist  # no frame stands out as untouched: every frame is a press
    return ref_i, dist


def load_images(source: str | Path, *, reference: str | None = None, pattern: str | None = None,
                mm_per_px: float | None = None, ball_radius_mm: float | None = None, labels: str | Path | None = None,
                markers: str | Path | None = None, profile=None,
                log: Callable[[str], None] | None = None) -> tuple[Capture, dict[str, Any]]:
    """Read a folder of images or a video into a :class:`Capture` (see the module docstring).

    Parameters
    ----------
    source : path
        Folder or video file.
    reference : str, optional
        Name of the no-contact frame: a file name or its stem; with ``pattern``, a press id; for a
        video, a frame index; or ``"build"``: every frame is a press and the reference is built
        from them (:func:`calibration.reference.build_reference`; needs ``ball_radius_mm``).
        Default: found automatically (:func:`auto_reference`), and built when no frame is
        clearly closer to the median frame than the others (:data:`CLEAN_RATIO`), or when the
        presses match a reference built from them clearly better than the found frame (needs
        ``ball_radius_mm``; :func:`calibration.reference.compare_with_built`).
    pattern : str, optional
        File-name template with ``{press}`` and ``{pattern}`` (folders only).
    mm_per_px : float
        Pixel pitch (mm); required (the capture layout needs it).
    ball_radius_mm : float, optional
        Stored as the ``ball_radius_mm`` attribute (calibrate uses it when not told).
    labels : path, optional
        CSV ``name,x,y,radius_px`` (:func:`read_labels_csv`).
    markers : "auto", "none", a mask image path, or None
        Printed gel markers (:func:`calibration.markers.resolve_markers`).
    profile : str, path or SensorProfile, optional
        A sensor profile (:func:`pipeline.capture.sensor_profiles.load_profile`): its pixel
        pitch and ball radius where ``mm_per_px`` / ``ball_radius_mm`` are not given, and frames
        of its camera stream cropped, rotated and resized to its resolution (frames already of
        that resolution are kept; any other size is an error).
    log : callable, optional
        Told, one line each, of the steps that take seconds (building a reference from the
        presses: about 12 s for 30 presses of 640 x 480 on one core).

    Returns
    -------
    capture : Capture
        ``frames (K, P, H, W, C)``, ``reference (P, H, W, C)``, dtype as the files.
    report : dict
        ``source``, ``presses``, ``patterns``, ``shape``, ``channels``, ``dtype``, ``bit_depth``,
        ``reference`` (the frame's name, or ``built``), ``reference_auto``, ``reference_found`` (the
        no-contact frame found or named, None when there is none), ``reference_comparison``
        (:func:`calibration.reference.compare_with_built`'s result, or None), ``reference_distance`` (:func:`auto_reference`'s
        distance to the median frame), ``next_closest_distance``, ``labels``, ``markers`` (pixels), ``mm_per_px``,
        ``ball_radius_mm``.
    """
    src = Path(source)
    say = log or (lambda message: None)
    prof, mm_per_px, ball_radius_mm = _import_scale(src, profile, mm_per_px, ball_radius_mm)
    names, frames, pattern_names, kind = _source_frames(src, pattern)
    if len(names) < 2:
        raise UserError(f"{src}: only {len(names)} frame(s); a capture needs a reference and at least one press")
    if prof is not None:
        frames = prof.fit_frames(frames, str(src))
    ref_i, dist, built, comparison = _choose_reference(src, names, frames, reference, ball_radius_mm, mm_per_px, say)
    keep = [i for i in range(len(names)) if i != ref_i]
    press_names = [names[i] for i in keep]
    found = names[ref_i] if ref_i is not None else None
    ref = frames[ref_i] if built is None else built[0]
    mask = None
    if markers is not None:
        from calibration.markers import resolve_markers

        mask = resolve_markers(markers, ref)
    lab = read_labels_csv(labels, press_names) if labels is not None else None
    p, c = frames.shape[1], frames.shape[-1]
    meta: dict[str, Any] = {
        "source": f"{kind}:{src.name}", "pattern_names": list(pattern_names),
        "mode": "trichromatic" if (p, c) == (1, 3) else "user-defined", "bit_depth": _BIT_DEPTH[frames.dtype],
        "frame_names": press_names, "original_file": src.name,
        "reference_name": found if built is None else "built",
        "reference_source": f"frame {found}" if built is None else built[1]["note"],
    }
    if ball_radius_mm is not None:
        meta["ball_radius_mm"] = float(ball_radius_mm)
    if prof is not None:
        meta["sensor_profile"] = prof.name
        # Recorded, not looked up later by name: a user's profile file is not found by its name.
        meta.update(prof.recorded_settings())
    # The drive is not known from files: each pattern is taken as its own light (P = 1 with three
    # colour channels: three LED groups, red, green and blue, as the GelSight import does).
    drive = np.eye(3, dtype=np.float32)[None] if (p, c) == (1, 3) else np.repeat(
        np.eye(p, dtype=np.float32)[..., None], 3, axis=2)
    if mask is not None:
        meta["markers_source"] = str(markers)
    cap = Capture(frames=np.ascontiguousarray(frames[keep]), reference=np.ascontiguousarray(ref), drive=drive,
                  brightness=np.ones(p, np.float32), mm_per_px=float(mm_per_px), labels=lab, meta=meta, markers=mask)
    report = _import_report(src, frames, keep, found, built, comparison, dist, ref_i, reference, lab, mask,
                            mm_per_px, ball_radius_mm, prof)
    return cap, report


def _import_report(src: Path, frames: np.ndarray, keep: list[int], found, built, comparison, dist, ref_i,
                   reference, lab, mask, mm_per_px: float, ball_radius_mm: float | None, prof) -> dict[str, Any]:
    """:func:`load_images`'s report: what was read, which reference was taken and how, and the
    shipped sensor profiles of the frames' size (when none was given)."""
    from pipeline.capture.sensor_profiles import profiles_of_size

    p, c = frames.shape[1], frames.shape[-1]
    others = None if dist is None else np.sort(np.delete(dist, ref_i) if ref_i is not None else dist)
    return {"source": str(src), "presses": len(keep), "patterns": int(p),
            "shape": [int(frames.shape[2]), int(frames.shape[3])],
            "channels": int(c), "dtype": str(frames.dtype), "bit_depth": _BIT_DEPTH[frames.dtype],
            "reference": found if built is None else "built", "reference_auto": reference is None,
            "reference_built": None if built is None else built[1], "reference_found": found,
            "reference_comparison": comparison,
            "reference_distance": None if dist is None or ref_i is None else float(dist[ref_i]),
            "next_closest_distance": None if others is None or not len(others) else float(others[0]),
            "labels": lab is not None, "markers": 0 if mask is None else int(mask.sum()),
            "mm_per_px": float(mm_per_px), "ball_radius_mm": ball_radius_mm,
            "profile": None if prof is None else prof.name,
            "matching_profiles": [] if prof is not None else profiles_of_size(frames.shape[3], frames.shape[2])}


def _import_scale(src: Path, profile, mm_per_px: float | None, ball_radius_mm: float | None):
    """``(profile or None, mm_per_px, ball_radius_mm)``: those given, else the sensor profile's;
    a UserError without a positive pixel pitch or with a radius that is not positive."""
    from pipeline.capture.sensor_profiles import load_profile

    prof = None
    if profile is not None:
        prof = load_profile(profile)
        mm_per_px = prof.mm_per_px if mm_per_px is None else mm_per_px
        ball_radius_mm = prof.ball_radius_mm if ball_radius_mm is None else ball_radius_mm
    if mm_per_px is None or not (np.isfinite(mm_per_px) and mm_per_px > 0):
        raise UserError(f"{src}: give the pixel pitch with --mm-per-px (a positive number of mm per pixel; got "
                        f"{mm_per_px})")
    if ball_radius_mm is not None and not (np.isfinite(ball_radius_mm) and ball_radius_mm > 0):
        raise UserError(f"{src}: --ball-radius must be a positive radius in mm, got {ball_radius_mm}")
    return prof, mm_per_px, ball_radius_mm


def _choose_reference(src: Path, names: list[str], frames: np.ndarray, reference: str | None,
                      ball_radius_mm: float | None, mm_per_px: float, say: Callable[[str], None]):
    """``(ref_i, dist, built, comparison)``: the no-contact frame's index (None when none is
    clean or ``build`` is asked for) and every frame's distance to the median frame
    (:func:`_reference_index`); the reference built from the presses (with its report) where
    there is no clean frame, or where, found automatically, a built one matches the presses
    clearly better (``comparison``: :func:`calibration.reference.compare_with_built`'s result)."""
    built, comparison = None, None
    ref_i, dist = _reference_index(src, names, frames, reference)
    if ref_i is None:
        if ball_radius_mm is None:
            raise UserError(f"{src}: no frame is clearly free of contact (closest to the median of all frames: "
                            f"{'-' if dist is None else f'{np.min(dist):.1f}'}, next "
                            f"{'-' if dist is None else f'{np.sort(dist)[1]:.1f}'}); name it with --reference NAME, "
                            "or give --ball-radius to build a reference from the presses (--reference build)")
        say(f"{src}: no clean frame found; building the reference from the {len(names)} presses")
        built = _built_reference(frames, ball_radius_mm / mm_per_px)
    if reference is None and ref_i is not None and ball_radius_mm is not None:
        keep = [i for i in range(len(names)) if i != ref_i]
        say(f"{src}: comparing the no-contact frame {names[ref_i]} with references built from the "
            f"{len(keep)} presses (--reference {Path(names[ref_i]).stem} skips this)")
        built, comparison = _prefer_built(frames[keep], frames[ref_i], ball_radius_mm / mm_per_px, names[ref_i])
    return ref_i, dist, built, comparison


def import_images(source: str | Path, out: str | Path, **kwargs) -> dict[str, Any]:
    """Import a folder of images or a video as ``capture.h5``; returns :func:`load_images`' report plus ``out``.

    Everything is read and checked before the file is written (atomically), so a failed
    import leaves no file and an existing one untouched. Keyword arguments as
    :func:`load_images`.
    """
    cap, report = load_images(source, **kwargs)
    write_capture(out, cap)
    return {"out": str(out), **report}
