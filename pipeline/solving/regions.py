"""Where a capture's frames are solved: its region, its printed gel markers, its no-contact reference.

Where to solve (:func:`capture_region`): the capture's ``mask`` dataset (an object's
silhouette: DiLiGenT's, ``iristac sim ps-object``'s), or a user's ``mask`` (``--mask``), which
replaces it. Only those pixels are read out of the frames and solved
(:class:`pipeline.normals.prepare.FramePrep`); every pixel outside is invalid in the results.
The calibration models read whole frames (pixel position is one of their inputs) and are
masked afterwards.

Printed gel markers (:func:`marker_mask`: the capture's ``markers``, else the calibration's,
or ``--markers auto|none|MASK.png``) are filled in before normals are solved
(:func:`pipeline.normals.prepare.fill_markers`), False in the normals' ``mask`` and True in their
``filled (H, W)``: the integrators integrate through them.
"""

from __future__ import annotations

import numpy as np

from pipeline.base.errors import UserError
from pipeline.normals.lights import LightSource

__all__ = ["capture_region", "marker_mask", "reference_frames"]


def marker_mask(cap, spec=None, lights: LightSource | None = None) -> np.ndarray | None:
    """The printed gel markers to fill in: ``(H, W)`` bool, or None.

    Parameters
    ----------
    cap : Record
        The capture (its ``markers`` dataset, its ``reference`` for ``auto``).
    spec : None, "none", "auto", path or ndarray
        None: the capture's own ``markers``, else the calibration's (``lights.markers``);
        ``"none"``: no markers; ``"auto"``: detected in the capture's reference
        (:func:`calibration.markers.detect_markers`); a mask image (non-zero = marker) or an
        ``(H, W)`` array.
    lights : LightSource, optional
    """
    from calibration.markers import resolve_markers

    H, W = cap.data["frames"].shape[2:4]
    if spec is None:
        if "markers" in cap.data:
            m = np.asarray(cap.data["markers"]).astype(bool)
        elif lights is not None and lights.markers is not None:
            m = np.asarray(lights.markers, bool)
            if m.shape != (H, W):
                raise UserError(f"the calibration's marker mask is {m.shape}, the capture's frames {(H, W)}")
        else:
            return None
        return m if m.any() else None
    if isinstance(spec, str) and spec == "auto":
        ref = reference_frames(cap)
        if ref is None:
            raise UserError(f"{cap.path or 'capture'}: --markers auto finds markers in the no-contact reference; the "
                            f"capture has none (give a mask image instead)")
        spec_ref = np.asarray(ref, np.float32)
        if "dark" in cap.data:
            spec_ref = spec_ref - np.asarray(cap.data["dark"], np.float32)
        m = resolve_markers("auto", spec_ref)
    else:
        m = resolve_markers(spec, np.zeros((1, H, W, 1), np.uint8))
    return None if m is None or not np.asarray(m).any() else np.asarray(m, bool)


def capture_region(cap, mask=None) -> np.ndarray | None:
    """The pixels to reconstruct: a user's ``mask`` (a ``.png``/``.npy`` path or an array), else
    the capture's ``mask`` dataset, else None (every pixel).

    Raises
    ------
    UserError
        Naming the mask file (or the capture and its dataset ``mask``) when the mask does not
        have the frames' ``(H, W)`` or selects no pixel.
    """
    import os

    H, W = cap.data["frames"].shape[2:4]
    if mask is None:
        if "mask" not in cap.data:
            return None
        m, where = np.asarray(cap.data["mask"]), f"{cap.path or 'capture'}: dataset 'mask'"
    elif isinstance(mask, (str, os.PathLike)):
        from pipeline.results.evaluate import load_mask

        m, where = load_mask(mask), f"{mask}: mask"
    else:
        m, where = np.asarray(mask), "mask"
    if m.shape != (H, W):
        raise UserError(f"{where} has shape {m.shape}, expected (H, W) = {(H, W)} to match the capture's frames")
    if m.dtype != bool:
        m = m != 0
    if not m.any():
        raise UserError(f"{where} selects no pixels (all zero): nothing to reconstruct")
    return m


def reference_frames(cap) -> np.ndarray | None:
    """The capture's no-contact ``reference (P, H, W, C)``, or None when it has none (the
    dataset is absent, or a version-1 file marked ``has_reference = False`` holds zeros)."""
    if "reference" not in cap.data or cap.meta.get("has_reference", True) is False:
        return None
    return cap.data["reference"]
