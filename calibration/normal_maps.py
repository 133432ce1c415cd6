"""One batched prediction API for every calibration model: frames -> normal maps.

Every model that :func:`calibration.calibrate.calibrate` fits (far, near, traced, lut, mlp)
predicts normals for :class:`calibration.samples.Samples`; this module turns that into what a
normal solver returns for whole frames, so that one wrapper can serve every model:

>>> import numpy as np
>>> from calibration.synthetic import synthetic_sphere_capture
>>> from calibration.calibrate import calibrate
>>> cap, _ = synthetic_sphere_capture((40, 50), 4, num_leds=4, peak_dn=140, seed=1)
>>> res = calibrate(cap, 1.5, models=["near"], folds=2, refine_iterations=0)
>>> frames, ref = cap.linear()
>>> nm = predict_normal_maps(res.models["near"], frames, ref)
>>> nm.normals.shape, nm.mask.shape, nm.confidence.shape, bool(np.isfinite(nm.normals).all())
((4, 40, 50, 3), (4, 40, 50), (4, 40, 50), True)

Contract (:class:`NormalMaps`): unit normals ``(N, H, W, 3)`` float32 in the reconstruction
frame, finite everywhere (the flat-gel normal ``(0, 0, 1)`` where a model has no answer);
``mask (N, H, W)`` True where the prediction is trustworthy; ``confidence (N, H, W)`` in
[0, 1], 0 outside the mask. What the confidence means depends on the model (the light
matrix's inverse condition number for light-field models, how much training data the LUT bin
held, the agreement of an MLP ensemble's members) and is named in ``meta["confidence"]``.

Printed gel markers (``markers (H, W)`` bool, see :mod:`calibration.markers`) are filled in
before the prediction and are False in the mask.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["NormalMaps", "predict_normal_maps", "pixel_samples", "as_frame_stack"]


@dataclass
class NormalMaps:
    """Per-pixel normals of N frames.

    Attributes
    ----------
    normals : ndarray, shape (N, H, W, 3), float32
        Unit normals (reconstruction frame, +z toward the camera); ``(0, 0, 1)`` where the
        mask is False and no filled-in value exists. Never NaN.
    mask : ndarray, shape (N, H, W), bool
        Trustworthy pixels.
    confidence : ndarray, shape (N, H, W), float32
        In [0, 1], 0 outside the mask.
    meta : dict
        ``model`` (name), ``confidence`` (what the confidence measures), ``markers`` (marker
        pixels per frame, when a marker mask was given).
    filled : ndarray, shape (H, W), bool, or None
        Marker pixels whose normals come from filled-in observations: False in ``mask`` (not a
        measurement) but fit to integrate through (``mask | filled``): treated as flat gel they
        would dent every cap they cross (on the real frames with drawn markers the fitted ball
        radius error went from 2.9 % to 6.1 %).
    """

    normals: np.ndarray
    mask: np.ndarray
    confidence: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    filled: np.ndarray | None = None


def as_frame_stack(frames: np.ndarray, num_patterns: int | None = None) -> np.ndarray:
    """Frames as a float32 ``(N, P, H, W, C)`` stack.

    Accepts ``(N, P, H, W, C)``, ``(N, H, W, C)`` (one pattern) and ``(H, W, C)`` (one frame
    of one pattern). With ``num_patterns`` given, a 4-D input whose first axis equals it is
    read as the P patterns of one frame.

    Examples
    --------
    >>> as_frame_stack(np.zeros((5, 6, 3))).shape
    (1, 1, 5, 6, 3)
    >>> as_frame_stack(np.zeros((4, 5, 6, 3)), num_patterns=4).shape
    (1, 4, 5, 6, 3)
    """
    f = np.asarray(frames, dtype=np.float32)
    if f.ndim == 3:
        return f[None, None]
    if f.ndim == 4:
        return f[None] if num_patterns is not None and num_patterns > 1 and f.shape[0] == num_patterns else f[:, None]
    if f.ndim == 5:
        return f
    raise ValueError(f"frames must be (N, P, H, W, C), (N, H, W, C) or (H, W, C), got shape {f.shape}")


def pixel_samples(image: np.ndarray, reference: np.ndarray, rows: np.ndarray | None = None,
                  cols: np.ndarray | None = None):
    """:class:`calibration.samples.Samples` of every pixel (or the given ones) of one frame.

    Parameters
    ----------
    image, reference : ndarray, shape (P, H, W, C)
    rows, cols : ndarray, shape (N,), optional
        Pixels to take (default: all, row-major).

    The ``normals`` of the returned samples are placeholders ``(0, 0, 1)``; ``press`` is 0 and
    ``contact`` False; ``images`` is the frame (``(1, P, H, W, C)``) and ``reference_image`` the
    reference, for models that look at a pixel's neighbourhood.
    """
    from calibration.samples import Samples

    p, h, w, c = image.shape
    if rows is None:
        rows, cols = (a.ravel() for a in np.mgrid[:h, :w])
    img = np.asarray(image, np.float32).transpose(1, 2, 0, 3)[rows, cols]
    ref = np.asarray(reference, np.float32).transpose(1, 2, 0, 3)[rows, cols]
    n = np.zeros((len(rows), 3))
    n[:, 2] = 1.0
    return Samples(img, ref, rows, cols, n, np.zeros(len(rows), int), np.zeros(len(rows), bool), (h, w), None,
                   np.asarray(image, np.float32)[None], np.asarray(reference, np.float32))


def predict_normal_maps(model, frames: np.ndarray, reference: np.ndarray | None = None, *,
                        markers: np.ndarray | None = None) -> NormalMaps:
    """Normals, mask and confidence of whole frames with a fitted calibration model.

    Parameters
    ----------
    model : CalibrationModel
        A fitted model (``calibrate(...).models[name]`` or :func:`calibration.stored.load_models`).
    frames : ndarray, shape (N, P, H, W, C) or (N, H, W, C) (P = 1)
        Linear frames: the same scale as the calibration capture with its dark level removed
        (``Capture.linear()``).
    reference : ndarray, shape (P, H, W, C), optional
        The no-contact frame of the session; default the one the model was calibrated with.
        The LUT and the MLP key on the change against it, so a reference taken in the same
        session as the frames removes drift.
    markers : ndarray, shape (H, W), bool, optional
        Printed marker pixels: filled in (:func:`pipeline.normals.prepare.fill_markers`) before the
        prediction and False in the mask.

    Returns
    -------
    NormalMaps
    """
    ref = reference if reference is not None else model.stored_reference()
    stack = as_frame_stack(frames, None if ref is None else np.asarray(ref).shape[0])
    n_img, p, h, w, c = stack.shape
    if ref is None:
        ref = np.zeros((p, h, w, c), np.float32)
    ref = np.asarray(ref, dtype=np.float32)
    if ref.shape != (p, h, w, c):
        raise ValueError(f"predict_normal_maps: reference must be (P, H, W, C) = {(p, h, w, c)} like the frames, got "
                         f"{ref.shape}")
    finite = np.isfinite(stack).all(axis=(1, 4))  # (N, H, W): a NaN anywhere in a pixel's observations
    stack = np.where(np.isfinite(stack), stack, 0.0).astype(np.float32)
    meta: dict[str, Any] = {"model": getattr(model, "name", type(model).__name__)}
    if markers is not None:
        from pipeline.normals.prepare import check_marker_mask, fill_markers

        markers = check_marker_mask(markers, (h, w))
        stack = fill_markers(stack, markers)
        ref = fill_markers(ref[None], markers)[0]
        meta["markers"] = int(markers.sum())
    normals = np.zeros((n_img, h, w, 3), np.float32)
    mask = np.zeros((n_img, h, w), bool)
    conf = np.zeros((n_img, h, w), np.float32)
    for i in range(n_img):
        n, ok, cf = model.predict_with_confidence(pixel_samples(stack[i], ref))
        n = np.asarray(n, np.float64).reshape(h, w, 3)
        ok = np.asarray(ok, bool).reshape(h, w) & np.isfinite(n).all(-1) & finite[i]
        n = np.where(np.isfinite(n), n, 0.0)
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        ok &= norm[..., 0] > 0.5
        n = np.where(ok[..., None], n / np.maximum(norm, 1e-12), np.array([0.0, 0.0, 1.0]))
        if markers is not None:
            ok &= ~markers  # a filled-in value is a guess, not a measurement
        normals[i] = n
        mask[i] = ok
        conf[i] = np.where(ok, np.clip(np.nan_to_num(np.asarray(cf, np.float64).reshape(h, w)), 0.0, 1.0), 0.0)
    meta["confidence"] = model.confidence_meaning
    return NormalMaps(normals=normals, mask=mask, confidence=conf, meta=meta, filled=markers)
