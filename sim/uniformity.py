"""Per-channel uniformity of lighting modes on a flat gel (the paper's section V question).

After channel separation, is each colour channel of each frame evenly lit? For every mode,
frame and lit camera channel we render the flat gel (no noise) and report, over the region of
interest:

``cv``
    coefficient of variation ``std / mean`` (0 = perfectly uniform);
``min_over_max``
    darkest over brightest pixel (1 = perfectly uniform);
``spread``
    ``(max - min) / mean``.

Examples
--------
>>> from sim.render import bare_ring_illumination
>>> model = bare_ring_illumination((24, 32), 0.5)
>>> rep = mode_uniformity(model, "multicolour")
>>> sorted(rep["channels"]), rep["frames"][0]["channels"]["R"]["lit"]
(['B', 'G', 'R'], True)
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from pipeline.base.frames import CHANNELS
from pipeline.base.modes import list_modes, load_mode, mode_brightness, mode_drive
from sim.figures import save_figure
from sim.illumination_model import IlluminationModel
from sim.render import RenderSettings, render_images

__all__ = ["channel_stats", "mode_uniformity", "uniformity_report", "uniformity_figure", "central_disc"]


def central_disc(shape: tuple[int, int], fraction: float = 0.9) -> np.ndarray:
    """Boolean mask (H, W) of the centred disc of diameter ``fraction * min(H, W)`` (the gel's active area).

    Examples
    --------
    >>> central_disc((5, 5), 1.0).sum()
    np.int64(21)
    """
    h, w = shape
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    r = np.hypot(rows - (h - 1) / 2, cols - (w - 1) / 2)
    return r <= fraction * min(h, w) / 2


def channel_stats(img: np.ndarray, region: np.ndarray | None = None) -> dict:
    """Uniformity numbers of one channel image (H, W) over ``region``.

    Examples
    --------
    >>> channel_stats(np.array([[1.0, 3.0]]))["cv"]
    0.5
    """
    img = np.asarray(img, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"channel_stats: expected an image (H, W), got {img.shape}")
    v = img[region] if region is not None else img.reshape(-1)
    mean = float(v.mean())
    if not mean > 0:
        return {"lit": False, "mean": mean, "cv": 0.0, "min_over_max": 0.0, "spread": 0.0}
    return {"lit": True, "mean": mean, "cv": float(v.std() / mean), "min_over_max": float(v.min() / v.max()),
            "spread": float((v.max() - v.min()) / mean)}


def _flat_images(model: IlluminationModel, mode) -> np.ndarray:
    drive, bright = mode_drive(mode), mode_brightness(mode)
    # exposure 1, no noise, float64: the radiance itself (uniformity is scale-free)
    return render_images(model, None, drive, bright, settings=RenderSettings(), dtype=torch.float64)


def mode_uniformity(model: IlluminationModel, mode, region: np.ndarray | None = None) -> dict:
    """Uniformity of every lit channel of every frame of one mode on the flat gel.

    Parameters
    ----------
    model : IlluminationModel
    mode : str, Path or LightingMode
    region : ndarray (H, W) bool, optional
        Pixels to assess (default :func:`central_disc`).

    Returns
    -------
    dict
        ``{"mode", "frames": [{"name", "channels": {"R": stats, ...}}], "channels": {"R":
        {"cv_mean", "cv_max", "min_over_max_min", "frames_lit"}}}``; a channel no frame
        lights has ``frames_lit = 0`` and no numbers.
    """
    mode = load_mode(mode)
    region = central_disc(model.shape) if region is None else np.asarray(region, bool)
    if region.shape != model.shape:
        raise ValueError(f"mode_uniformity: region must have shape {model.shape}, got {region.shape}")
    imgs = _flat_images(model, mode)
    frames = []
    for f, img in zip(mode.frames, imgs):
        frames.append({"name": f.name, "channels": {c: channel_stats(img[..., j], region)
                                                     for j, c in enumerate(CHANNELS)}})
    summary = {}
    for c in CHANNELS:
        lit = [fr["channels"][c] for fr in frames if fr["channels"][c]["lit"]]
        summary[c] = {"frames_lit": len(lit)}
        if lit:
            summary[c].update(cv_mean=float(np.mean([s["cv"] for s in lit])),
                              cv_max=float(np.max([s["cv"] for s in lit])),
                              min_over_max_min=float(np.min([s["min_over_max"] for s in lit])))
    return {"mode": mode.name, "frames": frames, "channels": summary}


def uniformity_report(model: IlluminationModel, modes: Sequence | None = None,
                      region: np.ndarray | None = None) -> dict:
    """:func:`mode_uniformity` of several modes (default: every built-in mode), keyed by name."""
    modes = list(modes) if modes is not None else list_modes()
    out = {}
    for m in modes:
        rep = mode_uniformity(model, m, region)
        out[rep["mode"]] = rep
    return out


def uniformity_figure(model: IlluminationModel, path, modes: Sequence | None = None,
                      ) -> Path:
    """Figure: per mode, the first frame's colour image and its separated R, G, B channels.

    Each channel image is shown on its own scale (0 to its maximum) with its CV and
    min/max in the title, so unevenness is visible whatever the brightness.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = list(modes) if modes is not None else list_modes()
    region = central_disc(model.shape)
    fig, axes = plt.subplots(len(modes), 4, figsize=(12, 2.7 * len(modes)), squeeze=False)
    for row, m in zip(axes, modes):
        mode = load_mode(m)
        imgs = _flat_images(model, mode)
        # the frame that lights the most channels (all of them for single-frame modes)
        k = int(np.argmax([(img.reshape(-1, 3).max(0) > 0).sum() for img in imgs]))
        img = imgs[k]
        row[0].imshow(np.clip(img / img.max(), 0, 1))
        row[0].set_title(f"{mode.name}: {mode.frames[k].name}")
        for j, c in enumerate(CHANNELS):
            ch = img[..., j]
            st = channel_stats(ch, region)
            row[j + 1].imshow(ch, cmap="gray", vmin=0, vmax=max(ch.max(), 1e-30))
            row[j + 1].set_title(f"{c}: cv {st['cv']:.3f}, min/max {st['min_over_max']:.2f}" if st["lit"]
                                 else f"{c}: unlit")
            row[j + 1].contour(region, levels=[0.5], colors="y", linewidths=0.6)
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    return save_figure(fig, path, dpi=80)
