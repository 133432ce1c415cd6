"""Overlay PNG: every press with its detected circle (green accepted, red rejected) and, when
the capture has them, the hand labels (white)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.detect import Circle
from pipeline.base.capture import Capture

__all__ = ["overlay_image", "write_overlay"]


def overlay_image(capture: Capture, circles: list[Circle], scale: int = 3, columns: int = 6) -> np.ndarray:
    """Montage ``(rows * H * scale, columns * W * scale, 3)`` uint8 RGB of the presses with circles."""
    import cv2

    frames = np.asarray(capture.frames, dtype=np.float32)[:, 0]  # first pattern, (K, H, W, C)
    if frames.shape[-1] != 3:
        frames = np.repeat(frames[..., :1], 3, axis=-1)
    top = max(float(np.percentile(frames, 99.5)), 1e-6)
    tiles = []
    for k, c in enumerate(circles):
        img = np.clip(frames[k] / top * 255.0, 0, 255).astype(np.uint8)
        img = np.ascontiguousarray(cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST))
        sh = 4  # cv2 draws with fixed-point sub-pixel coordinates

        def draw(cx, cy, r, colour):
            cv2.circle(img, (int(round((cx + 0.5) * scale * 2 ** sh)), int(round((cy + 0.5) * scale * 2 ** sh))),
                       int(round(r * scale * 2 ** sh)), colour, 1, cv2.LINE_AA, sh)

        if capture.labels is not None:
            draw(*capture.labels["center_xy"][k], float(capture.labels["radius_px"][k]), (255, 255, 255))
        draw(*c.center_xy, max(c.radius_px, 1.0), (0, 255, 0) if c.accepted else (255, 0, 0))
        if c.accepted:
            draw(*c.center_xy, c.contact_radius_px, (255, 255, 0))
        cv2.putText(img, str(k), (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)]
    return np.vstack(rows)


def write_overlay(path: str | Path, capture: Capture, circles: list[Circle]) -> Path:
    """Write :func:`overlay_image` as a PNG (converted to OpenCV's BGR on the way out)."""
    import cv2

    img = overlay_image(capture, circles, columns=min(6, max(1, len(circles))))
    path = Path(path)
    if not cv2.imwrite(str(path), img[..., ::-1]):
        from pipeline.base.errors import UserError

        raise UserError(f"{path}: could not write the overlay PNG")
    return path
