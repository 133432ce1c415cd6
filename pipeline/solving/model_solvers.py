"""The calibration's fitted models as photometric-stereo solvers (``--solver far|near|traced|lut|mlp``).

``iristac calibrate`` fits far-field, near-field, traced, lookup-table and MLP models
(:mod:`calibration.models`); every one of them predicts whole frames through its batched
``normal_maps(frames, reference, markers=...)`` (:mod:`calibration.normal_maps`). The adapters
here make each a solver of the registry (:data:`pipeline.base.registry.SOLVERS`), so that
``reconstruct``, ``batch``, ``compare-modes`` and live use apply a calibration *exactly* as
``iristac eval calibration`` does: one code path, the model's own (the LUT with its per-bin
position correction, every model with its fitted tilt gain).

They live in the calibration layer because a model is a calibration object, a layer above the
normal solvers (``tests/test_layers.py``); :func:`pipeline.solving.light_files.load_lights`
reads the models out of the calibration record.

What a model's :class:`~calibration.normal_maps.NormalMaps` becomes in a
:class:`~pipeline.normals.result.NormalResult`: normals and mask as they are; ``confidence``
as it is (what it measures is in ``meta["confidence"]``); ``condition`` the inverse of the
confidence for the light-field models (whose confidence *is* the light matrix's inverse
condition number), 1 for the table and the MLP (no light matrix); ``albedo`` 1 at valid pixels
and ``residual`` 0 (a model predicts no albedo); ``count`` the observations per pixel.
"""

from __future__ import annotations

import numpy as np

from pipeline.normals.result import COND_CAP

__all__ = ["solve_with_model", "maps_to_results", "stack_far", "stack_near", "stack_traced", "stack_lut",
           "stack_mlp", "stack_conv", "stack_conv_fast", "LIGHT_FIELD_MODELS"]

#: Models whose confidence is the inverse condition number of a per-pixel light matrix.
LIGHT_FIELD_MODELS = ("far", "near", "traced")


def maps_to_results(maps, name: str, observations: int) -> list:
    """One :class:`~pipeline.normals.result.NormalResult` per frame of a model's ``NormalMaps``.

    Parameters
    ----------
    maps : NormalMaps
        ``normals (N, H, W, 3)``, ``mask (N, H, W)``, ``confidence (N, H, W)``, ``meta``.
    name : str
        The model (and solver) name.
    observations : int
        Observations per pixel (P x C), reported as ``count`` at valid pixels.
    """
    from pipeline.normals.result import NormalResult

    out = []
    for k in range(maps.normals.shape[0]):
        ok = np.asarray(maps.mask[k], bool)
        conf = np.asarray(maps.confidence[k], np.float32)
        if name in LIGHT_FIELD_MODELS:
            cond = np.where(conf > 0, 1.0 / np.maximum(conf, 1.0 / COND_CAP), COND_CAP).astype(np.float32)
        else:
            cond = np.ones(ok.shape, np.float32)
        meta = {"solver": name, "model": name, "confidence": str(maps.meta.get("confidence", ""))}
        if "markers" in maps.meta:
            meta["markers"] = int(maps.meta["markers"])
        out.append(NormalResult(normals=np.asarray(maps.normals[k], np.float32), albedo=ok[..., None].astype(np.float32),
                                residual=np.zeros(ok.shape, np.float32), condition=cond, mask=ok,
                                count=np.where(ok, observations, 0).astype(np.int32), meta=meta, confidence=conf))
    return out


def solve_with_model(name: str, frames, lights, *, reference=None, markers=None, **_) -> list:
    """Normals of every contact instance with the calibration's model ``name``.

    Parameters
    ----------
    name : str
        ``far``, ``near``, ``traced``, ``lut`` or ``mlp`` (a key of ``lights.models``).
    frames : ndarray, shape (K, P, H, W, C)
        Dark-subtracted float frames (``Capture.linear()``).
    lights : LightSource
        With ``models`` (:func:`pipeline.solving.light_files.load_lights`).
    reference : ndarray, shape (P, H, W, C), optional
        The capture's dark-subtracted no-contact frames; None: the model's own (the one it was
        calibrated with).
    markers : ndarray, shape (H, W), bool, optional
        Printed gel markers, filled in by the model's ``normal_maps`` and False in the mask.

    Returns
    -------
    list of NormalResult
    """
    model = lights.models[name]
    frames = np.asarray(frames, np.float32)
    _, P, _, _, C = frames.shape
    maps = model.normal_maps(frames, reference, markers=markers)
    return maps_to_results(maps, name, P * C)


def stack_far(frames, lights, **options) -> list:
    """The calibration's far-field model (:func:`solve_with_model`)."""
    return solve_with_model("far", frames, lights, **options)


def stack_near(frames, lights, **options) -> list:
    """The calibration's polynomial near-field model (:func:`solve_with_model`)."""
    return solve_with_model("near", frames, lights, **options)


def stack_traced(frames, lights, **options) -> list:
    """The calibration's traced model (:func:`solve_with_model`)."""
    return solve_with_model("traced", frames, lights, **options)


def stack_lut(frames, lights, **options) -> list:
    """The calibration's lookup table, with its per-bin position correction (:func:`solve_with_model`)."""
    return solve_with_model("lut", frames, lights, **options)


def stack_mlp(frames, lights, **options) -> list:
    """The calibration's MLP (:func:`solve_with_model`)."""
    return solve_with_model("mlp", frames, lights, **options)


def stack_conv(frames, lights, **options) -> list:
    """The calibration's convolutional network (:func:`solve_with_model`)."""
    return solve_with_model("conv", frames, lights, **options)


def stack_conv_fast(frames, lights, **options) -> list:
    """The calibration's convolutional network on the frame shrunk by 2 (:func:`solve_with_model`)."""
    return solve_with_model("conv-fast", frames, lights, **options)
