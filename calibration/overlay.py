"""Overlay PNG: every press with its circle (green accepted, red rejected), the reason, and, when
the capture has them, the hand labels (white).

Each tile is a press's first pattern (scaled so the tile is about :data:`TILE_WIDTH` pixels wide,
whatever the frame size) above the difference to the reference (what the detector searched),
with the press number and its verdict written under them: ``ok``, a note (clamped radius, part
of the rim outside the image) or the reason it was rejected.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from calibration.detect import Circle, difference_image
from pipeline.base.capture import Capture

__all__ = ["TILE_WIDTH", "overlay_image", "write_overlay"]

#: Width (pixels) of one press's tile in the overlay.
TILE_WIDTH = 240


def _circle(im: np.ndarray, cx: float, cy: float, r: float, scale: float, colour) -> None:
    """Draw a circle given in frame pixels on a tile ``scale`` times the frame's size (sub-pixel)."""
    import cv2

    sh = 4  # cv2 draws with fixed-point sub-pixel coordinates
    cv2.circle(im, (round((cx + 0.5) * scale * 2 ** sh), round((cy + 0.5) * scale * 2 ** sh)),
               round(r * scale * 2 ** sh), colour, 1, cv2.LINE_AA, sh)


def _tile(frame: np.ndarray, diff: np.ndarray, circle: Circle, label, scale: float, top: float, index: int,
          text_rows: int) -> np.ndarray:
    import cv2

    img = np.clip(frame / top * 255.0, 0, 255).astype(np.uint8)
    d = np.clip(diff / max(float(np.percentile(diff, 99.5)), 1e-6) * 255.0, 0, 255).astype(np.uint8)
    d = np.repeat(d[..., None], 3, axis=2)
    parts = []
    for im in (img, d):
        im = np.ascontiguousarray(cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA
                                             if scale < 1 else cv2.INTER_NEAREST))
        if label is not None:
            _circle(im, *label, scale, (255, 255, 255))
        _circle(im, *circle.center_xy, max(circle.radius_px, 1.0), scale,
                (0, 255, 0) if circle.accepted else (255, 0, 0))
        if circle.accepted and circle.contact_radius_px < circle.radius_px:
            _circle(im, *circle.center_xy, circle.contact_radius_px, scale, (255, 255, 0))
        parts.append(im)
    w = parts[0].shape[1]
    band = np.zeros((14 * text_rows + 6, w, 3), np.uint8)
    status = "accepted" if circle.accepted else "REJECTED"
    lines = textwrap.wrap(f"{index}: {status}: {circle.reason}", max(12, w // 7))[:text_rows]
    for i, line in enumerate(lines):
        cv2.putText(band, line, (3, 13 + 14 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.38,
                    (200, 255, 200) if circle.accepted else (255, 160, 160), 1, cv2.LINE_AA)
    return np.vstack([parts[0], parts[1], band])


def overlay_image(capture: Capture, circles: list[Circle], scale: float | None = None, columns: int = 6,
                  text_rows: int = 4) -> np.ndarray:
    """Montage ``(rows * tile_h, columns * tile_w, 3)`` uint8 RGB of every press: frame and difference
    with its circle, and its verdict written under them.

    Parameters
    ----------
    capture : Capture
    circles : list of Circle
        One per press (accepted or not).
    scale : float, optional
        Pixels of the tile per frame pixel (default: tiles :data:`TILE_WIDTH` wide).
    columns, text_rows : int
    """
    frames = np.asarray(capture.frames, dtype=np.float32)
    ref = np.asarray(capture.reference, dtype=np.float32)
    if len(circles) != frames.shape[0]:
        raise ValueError(f"overlay_image: {frames.shape[0]} presses but {len(circles)} circles")
    first = frames[:, 0]  # first pattern, (K, H, W, C)
    if first.shape[-1] != 3:
        first = np.repeat(first[..., :1], 3, axis=-1)
    top = max(float(np.percentile(first, 99.5)), 1e-6)
    scale = float(scale) if scale else TILE_WIDTH / first.shape[2]
    labels = capture.labels if capture.labels and "center_xy" in capture.labels else None
    tiles = []
    for k, c in enumerate(circles):
        diff = difference_image(frames[k], ref, 0.0)
        lab = None
        if labels is not None:
            x, y = np.asarray(labels["center_xy"], float)[k]
            r = float(np.asarray(labels["radius_px"], float)[k])
            lab = (x, y, r) if np.isfinite([x, y, r]).all() else None
        tiles.append(_tile(first[k], diff, c, lab, scale, top, k, text_rows))
    columns = max(1, min(columns, len(tiles)))
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)]
    return np.vstack(rows)


def write_overlay(path: str | Path, capture: Capture, circles: list[Circle]) -> Path:
    """Write :func:`overlay_image` as a PNG (converted to OpenCV's BGR on the way out)."""
    import cv2

    img = overlay_image(capture, circles)
    path = Path(path)
    if not cv2.imwrite(str(path), img[..., ::-1]):
        from pipeline.base.errors import UserError

        raise UserError(f"{path}: could not write the overlay PNG")
    return path
