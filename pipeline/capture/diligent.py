"""Import the DiLiGenT photometric-stereo benchmark layout as a capture with far-field lights.

A DiLiGenT object folder holds ``filenames.txt`` (one image name per line),
``light_directions.txt`` (one unit vector per line), ``light_intensities.txt`` (RGB per line),
``mask.png``, the 16-bit RGB PNG images and optionally ``Normal_gt.mat`` (key ``Normal_gt``,
``H x W x 3``). Images are read at full bit depth (``cv2.IMREAD_UNCHANGED``: 8-bit readers
silently change results) and converted from OpenCV's BGR to RGB.

Frames: DiLiGenT's camera frame is x right, y up, z toward the camera, the same axes as our
reconstruction frame (:mod:`pipeline.base.frames`), so directions and normals are taken as they are.

The capture (schema ``capture``) gets: ``frames (1, P, H, W, 3)`` uint16, ``drive (P, P, 3)``
(image ``p`` lit by light ``p`` alone at its RGB intensity), ``brightness`` ones,
``lights/light_vectors (P, 3, 3)`` (direction times the channel's intensity: the far-field
calibration :func:`pipeline.workflows.reconstruct.reconstruct` uses when given no other), ``mask (H, W)``
(reconstruction then solves only those pixels), ``truth/normals (1, H, W, 3)`` when
``Normal_gt.mat`` exists. DiLiGenT has no no-contact frame, so the capture has no
``reference`` (``--ratio`` is refused; version-1 captures held zeros and ``has_reference =
False``). Pixel pitch is unknown: ``mm_per_px`` is 1 (heights come out in pixels).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.base.errors import UserError

__all__ = ["DiligentObject", "read_diligent", "diligent_record", "import_diligent"]


@dataclass
class DiligentObject:
    """The contents of one DiLiGenT object folder.

    names (P,) image file names; directions (P, 3) unit light directions; intensities (P, 3)
    RGB light intensities; images (P, H, W, 3) RGB at full bit depth; mask (H, W) bool;
    normals_gt (H, W, 3) or None; folder the source folder.
    """

    names: list[str]
    directions: np.ndarray
    intensities: np.ndarray
    images: np.ndarray
    mask: np.ndarray
    normals_gt: np.ndarray | None
    folder: Path


def _read_table(path: Path, cols: int) -> np.ndarray:
    if not path.exists():
        raise UserError(f"{path}: missing (a DiLiGenT folder has filenames.txt, light_directions.txt, "
                        f"light_intensities.txt, mask.png)")
    try:
        a = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise UserError(f"{path}: expected {cols} numbers per line ({exc})") from None
    if a.shape[1] != cols:
        raise UserError(f"{path}: expected {cols} numbers per line, got {a.shape[1]}")
    return a


def _read_png(path: Path) -> np.ndarray:
    import cv2

    if not path.exists():
        raise UserError(f"{path}: image listed in filenames.txt is missing")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise UserError(f"{path}: cannot read the image")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.ndim != 3 or img.shape[-1] not in (3, 4):
        raise UserError(f"{path}: expected an RGB image, got shape {img.shape}")
    return img[..., 2::-1]  # BGR(A) -> RGB


def read_diligent(folder) -> DiligentObject:
    """Read a DiLiGenT object folder.

    Raises :class:`UserError` naming the file and what was expected.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"{folder}: not a folder")
    list_path = folder / "filenames.txt"
    if not list_path.exists():
        raise UserError(f"{list_path}: missing (expected one image file name per line)")
    names = [ln.strip() for ln in list_path.read_text().splitlines() if ln.strip()]
    if not names:
        raise UserError(f"{list_path}: no image names")
    dirs = _read_table(folder / "light_directions.txt", 3)
    ints = _read_table(folder / "light_intensities.txt", 3)
    for path, a in ((folder / "light_directions.txt", dirs), (folder / "light_intensities.txt", ints)):
        if len(a) != len(names):
            raise UserError(f"{path}: {len(a)} lines, but filenames.txt lists {len(names)} images")
    if len(names) < 3:
        raise UserError(f"{list_path}: lists {len(names)} image(s); photometric stereo needs at least 3 lights")
    images = np.stack([_read_png(folder / n) for n in names])
    shapes = {im.shape for im in images}
    if len(shapes) != 1:
        raise UserError(f"{folder}: images differ in size: {sorted(shapes)}")
    H, W = images.shape[1:3]
    mask_path = folder / "mask.png"
    if mask_path.exists():
        from pipeline.results.evaluate import load_mask

        mask = load_mask(mask_path)
        if mask.shape != (H, W):
            raise UserError(f"{mask_path}: shape {mask.shape}, the images are {(H, W)}")
        if not mask.any():
            raise UserError(f"{mask_path}: the mask selects no pixels (all zero)")
    else:
        mask = np.ones((H, W), bool)
    gt = None
    gt_path = folder / "Normal_gt.mat"
    if gt_path.exists():
        from pipeline.results.evaluate import load_normals

        gt, _ = load_normals(gt_path, key="Normal_gt")
        if gt.shape != (H, W, 3):
            raise UserError(f"{gt_path}: Normal_gt has shape {gt.shape}, expected {(H, W, 3)}")
    return DiligentObject(names, dirs, ints, images, mask, gt, folder)


def diligent_record(obj: DiligentObject):
    """The capture :class:`pipeline.base.store.Record` of a DiLiGenT object."""
    from pipeline.base.store import Record

    P = len(obj.names)
    frames = obj.images.astype(np.uint16 if obj.images.dtype.itemsize <= 2 else obj.images.dtype)[None]
    drive = np.zeros((P, P, 3), np.float32)
    drive[np.arange(P), np.arange(P)] = obj.intensities
    lights = (obj.directions[:, None, :] * obj.intensities[:, :, None]).astype(np.float32)  # (P, C, 3)
    data = {"frames": frames, "drive": drive, "brightness": np.ones(P, np.float32),
            "lights/light_vectors": lights, "mask": obj.mask}
    if obj.normals_gt is not None:
        data["truth/normals"] = obj.normals_gt.astype(np.float32)[None]
    bits = 16 if frames.dtype == np.uint16 else 8 * frames.dtype.itemsize
    meta = {"mm_per_px": 1.0, "pattern_names": list(obj.names), "source": "diligent", "mode": "point",
            "bit_depth": int(bits), "exposure": 1.0, "object": obj.folder.name}
    return Record("capture", data, meta)


def import_diligent(folder, out) -> dict:
    """Read a DiLiGenT folder and write it as ``out`` (capture.h5). Returns a summary dict
    with keys ``out``, ``images``, ``height``, ``width``, ``mask_pixels``, ``has_ground_truth``."""
    from pipeline.base.capture import write_capture

    obj = read_diligent(folder)
    path = write_capture(out, diligent_record(obj))
    return {"out": str(path), "images": len(obj.names), "height": int(obj.images.shape[1]),
            "width": int(obj.images.shape[2]), "mask_pixels": int(obj.mask.sum()),
            "has_ground_truth": obj.normals_gt is not None}
