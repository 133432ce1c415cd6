"""Imports of ball presses as ``capture.h5``: the GelSight-style ``.npz`` (here) and a folder of
images or a video (:mod:`calibration.image_import`, re-exported: :func:`import_images`).

The npz holds ``background (H, W, 3)``, ``images (K, H, W, 3)`` (uint8, **BGR**: read with
OpenCV), hand labels ``touch_center_xy (K, 2)`` and ``touch_radius_px (K,)``, ``names``,
``ball_radius_mm`` and ``mm_per_px``. The capture gets one pattern (P = 1: all LEDs on, the
three camera channels act as three lights), the background as its reference, channels in RGB
order, a drive of three LED groups (red, green, blue), and the labels as optional
``labels/*`` datasets that calibration reports against (and fits to with ``circles="labels"``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.image_import import import_images, load_images  # folders of images and videos
from pipeline.base.capture import Capture, write_capture
from pipeline.base.errors import UserError

__all__ = ["load_gelsight_npz", "import_gelsight_npz", "import_images", "load_images"]

_REQUIRED = {"background": 3, "images": 4}


def load_gelsight_npz(path: str | Path) -> Capture:
    """Read a GelSight-style npz into a :class:`Capture` (RGB, P = 1)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file (expected a GelSight-style .npz)")
    try:
        npz = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a readable .npz file ({exc})") from None
    with npz:
        for key, ndim in _REQUIRED.items():
            if key not in npz.files:
                raise UserError(f"{path}: missing array '{key}' (have {', '.join(npz.files)})")
            if npz[key].ndim != ndim or npz[key].shape[-1] != 3:
                raise UserError(f"{path}: '{key}' must have {ndim} dims ending in 3 (BGR), got {npz[key].shape}")
        bg, imgs = npz["background"], npz["images"]
        if imgs.shape[1:] != bg.shape:
            raise UserError(f"{path}: 'images' {imgs.shape} and 'background' {bg.shape} differ in size")
        labels = None
        if "touch_center_xy" in npz.files and "touch_radius_px" in npz.files:
            c, r = npz["touch_center_xy"], npz["touch_radius_px"]
            if c.shape != (len(imgs), 2) or r.shape != (len(imgs),):
                raise UserError(f"{path}: labels 'touch_center_xy' {c.shape} / 'touch_radius_px' {r.shape} do not "
                                f"match {len(imgs)} images (expected (K, 2) and (K,))")
            labels = {"center_xy": c.astype(np.float32), "radius_px": r.astype(np.float32)}
        meta = {"source": "gelsight-npz", "pattern_names": ["all-rgb"], "mode": "trichromatic", "bit_depth": 8,
                "original_file": path.name}
        if "names" in npz.files:
            meta["frame_names"] = [str(n) for n in npz["names"]]
        if "ball_radius_mm" in npz.files:
            meta["ball_radius_mm"] = float(npz["ball_radius_mm"])
        mm = float(npz["mm_per_px"]) if "mm_per_px" in npz.files else None
    # OpenCV frames are BGR; the project is RGB everywhere (pipeline.base.frames.CHANNELS).
    frames = np.ascontiguousarray(imgs[:, None, ..., ::-1])
    reference = np.ascontiguousarray(bg[None, ..., ::-1])
    return Capture(frames=frames, reference=reference, drive=np.eye(3, dtype=np.float32)[None],
                   brightness=np.ones(1, np.float32), mm_per_px=mm, labels=labels, meta=meta)


def import_gelsight_npz(path: str | Path, out: str | Path) -> dict:
    """Convert a GelSight-style npz to ``capture.h5``; returns a summary dict.

    Returns
    -------
    dict
        ``out``, ``presses``, ``shape`` (H, W), ``labels`` (bool), ``mm_per_px``.
    """
    cap = load_gelsight_npz(path)
    if cap.mm_per_px is None:
        raise UserError(f"{path}: no 'mm_per_px' array; the capture layout needs the pixel pitch")
    write_capture(out, cap)
    return {"out": str(out), "presses": int(cap.frames.shape[0]), "shape": list(cap.shape),
            "labels": cap.labels is not None, "mm_per_px": cap.mm_per_px}
