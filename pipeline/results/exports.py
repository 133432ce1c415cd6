"""Files for other tools: a normal-map PNG, a colour-mapped depth PNG and a PLY point cloud.

Conventions (stated in every file we can annotate, since unclear point-cloud origin and scale
is a common complaint about tactile SDKs): reconstruction frame, millimetres, origin on the
optical axis at the undeformed gel surface, ``x`` along columns, ``y`` up the image, ``z``
(height) toward the camera. PNGs are written RGB-correct (OpenCV wants BGR on disk).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.base.frames import pixel_to_recon

__all__ = ["normal_map_rgb", "depth_colormap_rgb", "png_bytes", "write_png", "write_normal_png", "write_depth_png",
           "write_ply", "write_pictures", "link_results"]


def normal_map_rgb(normals, mask=None) -> np.ndarray:
    """The usual normal-map encoding ``(n + 1) / 2 * 255`` as uint8 ``(H, W, 3)``; black where
    ``mask`` is False.

    Examples
    --------
    >>> n = np.zeros((1, 2, 3)); n[..., 2] = 1.0
    >>> normal_map_rgb(n, np.array([[True, False]])).tolist()
    [[[128, 128, 255], [0, 0, 0]]]
    """
    n = np.asarray(normals, dtype=np.float64)
    if n.ndim != 3 or n.shape[-1] != 3:
        raise ValueError(f"normal_map_rgb: normals must have shape (H, W, 3), got {n.shape}")
    rgb = np.round((np.clip(np.nan_to_num(n), -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)
    if mask is not None:
        rgb[~np.asarray(mask, bool)] = 0
    return rgb


def depth_colormap_rgb(height, mask=None, *, vmin: float | None = None, vmax: float | None = None,
                       cmap: str = "viridis") -> np.ndarray:
    """Heights ``(H, W)`` mapped through a matplotlib colour map to uint8 RGB ``(H, W, 3)``.

    The range defaults to the valid heights' min and max; invalid pixels are black.

    Examples
    --------
    >>> depth_colormap_rgb(np.array([[0.0, 1.0]])).shape
    (1, 2, 3)
    """
    import matplotlib

    h = np.asarray(height, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"depth_colormap_rgb: height must have shape (H, W), got {h.shape}")
    m = np.isfinite(h) if mask is None else (np.asarray(mask, bool) & np.isfinite(h))
    vals = h[m]
    lo = float(vals.min()) if vmin is None and vals.size else (0.0 if vmin is None else vmin)
    hi = float(vals.max()) if vmax is None and vals.size else (1.0 if vmax is None else vmax)
    t = np.clip((np.nan_to_num(h) - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0)
    rgb = (matplotlib.colormaps[cmap](t)[..., :3] * 255 + 0.5).astype(np.uint8)
    rgb[~m] = 0
    return rgb


def png_bytes(rgb) -> bytes:
    """An RGB (H, W, 3) or grey (H, W) uint8/uint16 image as PNG file bytes (for a web page).

    Examples
    --------
    >>> png_bytes(np.zeros((2, 3, 3), np.uint8))[:4]
    b'\\x89PNG'
    """
    import cv2

    img = np.asarray(rgb)
    if img.ndim == 3 and img.shape[-1] == 3:
        img = img[..., ::-1]  # OpenCV encodes BGR
    elif img.ndim != 2:
        raise ValueError(f"png_bytes: image must have shape (H, W, 3) or (H, W), got {img.shape}")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:  # pragma: no cover - cv2 encodes any uint8/uint16 image
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def write_png(path, rgb) -> Path:
    """Write an RGB uint8/uint16 image ``(H, W, 3)`` as PNG (converted to BGR for OpenCV)."""
    import cv2

    path = Path(path)
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise ValueError(f"write_png: image must have shape (H, W, 3), got {rgb.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"{path}: could not write PNG")
    return path


def write_normal_png(path, normals, mask=None) -> Path:
    """Normal map ``(H, W, 3)`` as a PNG (see :func:`normal_map_rgb`)."""
    return write_png(path, normal_map_rgb(normals, mask))


def write_depth_png(path, height, mask=None, **kwargs) -> Path:
    """Colour-mapped height map ``(H, W)`` as a PNG (see :func:`depth_colormap_rgb`)."""
    return write_png(path, depth_colormap_rgb(height, mask, **kwargs))


def write_ply(path, height, mm_per_px: float, mask=None, colors=None, *, binary: bool = True) -> Path:
    """Valid pixels of a height map as a PLY point cloud (mm, reconstruction frame).

    Parameters
    ----------
    height : ndarray, shape (H, W)
        Heights in mm.
    mm_per_px : float
        Pixel pitch; ``x, y`` follow :func:`pipeline.base.frames.pixel_to_recon` (origin on the axis).
    mask : ndarray, shape (H, W), bool, optional
        Only these pixels become vertices.
    colors : ndarray, shape (H, W, 3), uint8, optional
        Vertex colours (e.g. the captured frame or the normal map).

    Returns
    -------
    Path

    Examples
    --------
    >>> import tempfile, os
    >>> from plyfile import PlyData
    >>> p = write_ply(os.path.join(tempfile.mkdtemp(), "d.ply"), np.array([[0.0, 0.5]]), 0.1)
    >>> v = PlyData.read(str(p))["vertex"]
    >>> v["x"].tolist(), v["z"].tolist()
    ([-0.05000000074505806, 0.05000000074505806], [0.0, 0.5])
    """
    from plyfile import PlyData, PlyElement

    h = np.asarray(height, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"write_ply: height must have shape (H, W), got {h.shape}")
    m = np.isfinite(h) if mask is None else (np.asarray(mask, bool) & np.isfinite(h))
    rows, cols = np.nonzero(m)
    x, y = pixel_to_recon(rows, cols, h.shape, mm_per_px)
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if colors is not None:
        c = np.asarray(colors)
        if c.shape != h.shape + (3,):
            raise ValueError(f"write_ply: colors must have shape {h.shape + (3,)}, got {c.shape}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(len(rows), dtype=fields)
    v["x"], v["y"], v["z"] = x, y, h[rows, cols]
    if colors is not None:
        v["red"], v["green"], v["blue"] = (c[rows, cols, i] for i in range(3))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    comments = ["iristac height map: units mm, reconstruction frame (z toward the camera)",
                f"origin on the optical axis at the undeformed gel; mm_per_px {mm_per_px:g}"]
    PlyData([PlyElement.describe(v, "vertex")], text=not binary, comments=comments).write(str(path))
    return path


def write_pictures(out: Path, n_rec, d_rec, mm_per_px: float, contact=None) -> list[Path]:
    """Per contact instance ``normals_kNNN.png``, ``depth_kNNN.png`` and ``depth_kNNN.ply`` (and
    ``contact_kNNN.png`` from ``contact (K, H, W)`` bool, :mod:`pipeline.frame_pipeline.contact`) in ``out``, from
    the ``normals`` and ``depth`` records (their datasets read an instance at a time); the files
    written."""
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for k in range(n_rec.data["normals"].shape[0]):
        n, nm = np.asarray(n_rec.data["normals"][k], np.float32), n_rec.data["mask"][k]
        h, hm = d_rec.data["height"][k], d_rec.data["mask"][k]
        files.append(write_normal_png(out / f"normals_k{k:03d}.png", n, nm))
        files.append(write_depth_png(out / f"depth_k{k:03d}.png", h, hm))
        files.append(write_ply(out / f"depth_k{k:03d}.ply", h, mm_per_px, hm, colors=normal_map_rgb(n, nm)))
        if contact is not None:
            files.append(write_png(out / f"contact_k{k:03d}.png",
                                   np.repeat(np.asarray(contact[k])[..., None] * np.uint8(255), 3, -1)))
    return files


def link_results(out: Path, entries: dict) -> list[Path]:
    """``out/<name>.h5`` for each ``name -> store file`` of ``entries``: a hard link to the store's
    file (a symbolic link where ``out`` is on another file system), never a second copy; what was
    there is replaced atomically. The files linked."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for name, src in entries.items():
        src, dst = Path(src), out / f"{name}.h5"
        tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
        tmp.unlink(missing_ok=True)
        try:
            os.link(src, tmp)
        except OSError:
            os.symlink(src.resolve(), tmp)
        os.replace(tmp, dst)
        files.append(dst)
    return files
