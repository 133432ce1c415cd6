"""Frame preparation: what camera frames go through before a solver sees them, and its results after.

Every solve path (``reconstruct``, ``batch`` and ``run`` through the normals stage; ``live``
through its per-frame solver, eager or fast) prepares frames in one way, held by a
:class:`FramePrep`::

    raw frames ─► saturated = raw at full scale ─► float32 − dark ─► fill printed markers ─► region's pixels
                                                                     (unless the solver        (gathered once;
                                                                      fills them itself)        whole-frame solvers:
                                                                                                 restricted after)
               ─► illumination drift removed (each frame set's, against the no-contact reference)
    solver ─► results ─► scattered back to the frame ─► marker pixels invalid (a filled-in value is a guess)

Illumination drift (``drift``, :mod:`pipeline.normals.drift`): LEDs warm up, exposure wanders,
and a no-contact reference taken minutes (or a calibration taken days) before the frames no
longer matches their lighting. Where the solver keys on that reference (a calibration's model:
the LUT and the MLP take the colour change against it; the ratio to the reference), each frame
set's drift against it (per pattern-channel gain and offset, :data:`~pipeline.normals.drift.AUTO_DRIFT`)
is fitted on a fixed sample of the pixels, trimmed so that the contact drops out, and removed
(:meth:`FramePrep.use_drift`, called by :class:`pipeline.normals.solve.FrameSolver` once the
reference is known; ``drift="none"`` turns it off, a model name asks for it anywhere a reference
exists). The live fast paths fit the same drift from the same pixels and apply it inside their
kernels.

Whether a solver fills markers itself, or reads whole frames, is a fact of its registry entry
(``info["fills_markers"]``, ``info["whole_frame"]`` in :data:`pipeline.base.registry.SOLVERS`).
The fast per-frame paths (:mod:`pipeline.normals.fast`, :mod:`pipeline.normals.fast_models`)
take the same :class:`FramePrep` and do its steps inside their compiled kernels (the dark
level and the region); they do not fill markers, so with markers the eager path runs.

Marker filling is an image operation (:func:`fill_markers`, OpenCV inpainting); the
calibration's models use it too (:func:`calibration.normal_maps.predict_normal_maps`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.base.errors import UserError
from pipeline.normals.drift import SAMPLES, DriftEstimator, resolve_drift

__all__ = ["FramePrep", "fill_markers", "check_marker_mask", "full_scale"]


def check_marker_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``mask`` as bool ``(H, W)`` (or ``(N, H, W)``), checked against the image ``shape``.

    Examples
    --------
    >>> check_marker_mask(np.ones((2, 3)), (2, 3)).dtype
    dtype('bool')
    """
    m = np.asarray(mask)
    if m.shape[-2:] != tuple(shape) or m.ndim not in (2, 3):
        raise ValueError(f"marker mask must be (H, W) = {tuple(shape)} (or (N, H, W)), got {m.shape}")
    return m.astype(bool)


def fill_markers(frames: np.ndarray, mask: np.ndarray, *, radius_px: float = 3.0) -> np.ndarray:
    """Fill marker pixels from their surroundings (OpenCV Telea inpainting), every frame and channel.

    Parameters
    ----------
    frames : ndarray, shape (..., H, W, C)
        Any stack of frames (``(N, P, H, W, C)``, ``(P, H, W, C)``, ``(H, W, C)``).
    mask : ndarray, shape (H, W) or (N, H, W), bool
        Marker pixels; ``(N, H, W)`` gives each of the N leading frames its own mask.
    radius_px : float
        Neighbourhood the inpainting draws from.

    Returns
    -------
    ndarray, float32, same shape as ``frames``
        Unchanged outside the mask.

    Examples
    --------
    A smooth ramp with a hole is filled close to the ramp:

    >>> img = np.tile(np.linspace(0, 100, 32, dtype=np.float32), (24, 1))[..., None]
    >>> m = np.zeros((24, 32), bool); m[10:13, 15:18] = True
    >>> bad = img.copy(); bad[m] = 0
    >>> out = fill_markers(bad, m)
    >>> float(np.abs(out - img)[m].max()) < 4, bool((out[~m] == img[~m]).all())
    (True, True)
    """
    import cv2

    f = np.asarray(frames, np.float32)
    m = np.asarray(mask, bool)
    if f.ndim < 3:
        raise ValueError(f"fill_markers: frames must be (..., H, W, C), got {f.shape}")
    h, w, c = f.shape[-3:]
    m = check_marker_mask(m, (h, w))
    lead = f.shape[:-3]
    flat = f.reshape(-1, h, w, c).copy()
    per_frame = m.ndim == 3
    if per_frame and (not lead or m.shape[0] != lead[0]):
        raise ValueError(f"fill_markers: a per-frame mask (N, H, W) needs frames (N, ..., H, W, C), got {f.shape} "
                         f"and {m.shape}")
    group = int(np.prod(lead[1:])) if per_frame else 1
    for i in range(len(flat)):
        mi = m[i // group] if per_frame else m
        if not mi.any():
            continue
        m8 = mi.astype(np.uint8)
        for ch in range(c):
            flat[i, :, :, ch] = cv2.inpaint(np.ascontiguousarray(flat[i, :, :, ch]), m8, float(radius_px),
                                            cv2.INPAINT_TELEA)
    return flat.reshape(f.shape)


def full_scale(dtype, bit_depth: int | None = None) -> float | None:
    """The raw value of a saturated pixel: ``2**bit_depth - 1``, else the integer type's maximum,
    else None (float frames: no saturation known).

    Examples
    --------
    >>> full_scale(np.uint16, 12), full_scale(np.uint8), full_scale(np.float32)
    (4095, 255, None)
    """
    dt = np.dtype(dtype)
    if bit_depth:
        return 2 ** int(bit_depth) - 1
    return int(np.iinfo(dt).max) if dt.kind in "iu" else None


@dataclass
class FramePrep:
    """How frames of one sensor are prepared for a solver (see the module docstring).

    Parameters
    ----------
    shape : (H, W)
        The frames' image size.
    dark : ndarray, shape (H, W, C), optional
        The dark level (raw units), subtracted first.
    markers : ndarray, shape (H, W), bool, optional
        Printed gel markers: filled in before the solve (or handed to a solver that
        ``fills_markers``), invalid in every result.
    fills_markers : bool
        The solver fills markers itself (its registry entry's ``info["fills_markers"]``).
    region : ndarray, shape (H, W), bool, optional
        The pixels to solve; the others are invalid in every result.
    whole_frame : bool
        The solver reads whole frames (``info["whole_frame"]``): the region is applied to its
        results, not gathered from the frames.
    saturation : float, optional
        Raw value at full scale (:func:`full_scale`); such observations are flagged.
    name : str
        Who the frames are (a capture file): errors start with it.
    drift : str
        The illumination drift to remove: ``auto`` (where the solver keys on the reference),
        ``none`` or a model of :data:`pipeline.normals.drift.DRIFT_MODELS`; resolved, against a
        reference, by :meth:`use_drift`.
    drift_samples : int
        Pixels each frame set's drift is fitted on (:data:`pipeline.normals.drift.SAMPLES`; live
        uses fewer, :data:`~pipeline.normals.drift.LIVE_SAMPLES`).
    drift_every : int
        Fit the drift on every N-th frame set, reuse it in between (1: every one; live:
        :data:`~pipeline.normals.drift.LIVE_REFIT_EVERY`).

    Examples
    --------
    >>> prep = FramePrep((2, 3), dark=np.ones((2, 3, 1)), region=np.eye(2, 3, dtype=bool), saturation=255)
    >>> frames, saturated = prep.frames(np.full((1, 1, 2, 3, 1), 255, np.uint8))
    >>> frames.shape, float(frames.max()), bool(saturated.all())
    ((1, 1, 1, 2, 1), 254.0, True)
    """

    shape: tuple[int, int]
    dark: np.ndarray | None = None
    markers: np.ndarray | None = None
    fills_markers: bool = False
    region: np.ndarray | None = None
    whole_frame: bool = False
    saturation: float | None = None
    name: str = "frames"
    drift: str = "none"
    drift_samples: int = SAMPLES
    drift_every: int = 1
    pixels: object = field(init=False, default=None)
    #: The drift estimator against the reference (:meth:`use_drift`), None: no drift removed.
    estimator: object = field(init=False, default=None)
    #: The drifts fitted by the last :meth:`frames` call, one per frame set.
    drifts: list = field(init=False, default_factory=list)

    def __post_init__(self):
        self.shape = (int(self.shape[0]), int(self.shape[1]))
        if self.markers is not None:
            self.markers = np.asarray(self.markers, bool)
            if self.markers.shape != self.shape:
                raise UserError(f"marker mask has shape {self.markers.shape}, expected (H, W) = {self.shape} like the "
                                f"frames")
        if self.region is not None and not self.whole_frame:
            # Gather the region once, from the raw frames (no full-frame float copy) when no
            # marker needs filling (filling needs each marker's neighbourhood, so the gather
            # then follows the fill); the solver then sees only its pixels.
            from pipeline.normals.masking import PixelMask

            self.pixels = PixelMask(self.region, self.shape, f"{self.name}: mask")

    @property
    def drift_model(self) -> str:
        """The drift model removed (``none`` until :meth:`use_drift` resolved one)."""
        return "none" if self.estimator is None else self.estimator.model

    def use_drift(self, reference, *, applies: bool, linear: bool = False) -> str:
        """Resolve :attr:`drift` against ``reference (P, H, W, C)`` (raw, or ``linear``: dark level
        already removed; None: none exists) and, unless that is ``none``, fit each later frame
        set's drift against it and remove it (:class:`pipeline.normals.drift.DriftEstimator`; the
        pixels never fitted: markers, and those outside the region). ``applies``: the solver keys
        on the reference (what ``auto`` asks). Returns the model.

        Examples
        --------
        >>> prep = FramePrep((20, 30), drift="auto")
        >>> ref = np.tile(np.linspace(40, 200, 30, dtype=np.float32)[None, None, :, None], (1, 20, 1, 3))
        >>> prep.use_drift(ref, applies=True)
        'gain_offset'
        >>> frames, _ = prep.frames((0.8 * ref + 9)[None])   # 20 % darker, 9 DN up
        >>> round(float(prep.drifts[0].gain[0, 0, 0]), 2), float(np.abs(frames[0] - ref).max()) < 0.5
        (0.8, True)
        """
        model = resolve_drift(self.drift, applies=applies, has_reference=reference is not None, where=self.name)
        self.estimator = None
        if model == "none":
            return model
        ref = np.asarray(reference).astype(np.float32)
        if ref.ndim != 4 or ref.shape[1:3] != self.shape:
            raise UserError(f"{self.name}: the no-contact reference has shape {ref.shape}, expected (P, H, W, C) with "
                            f"(H, W) = {self.shape} like the frames")
        if not linear and self.dark is not None:
            ref = ref - np.asarray(self.dark).astype(np.float32)
        exclude = None if self.markers is None else self.markers.copy()
        if self.region is not None:
            outside = ~np.asarray(self.region, bool)
            exclude = outside if exclude is None else exclude | outside
        self.estimator = DriftEstimator(ref, exclude, model=model, max_samples=self.drift_samples,
                                        refit_every=self.drift_every)
        return model

    def reset_drift(self) -> None:
        """Start the drift fits over (the next frame set is fitted): after a warm-up frame."""
        if self.estimator is not None:
            self.estimator.reset()

    @property
    def fills_here(self) -> bool:
        """Whether markers are filled in here (not by the solver)."""
        return self.markers is not None and not self.fills_markers

    @property
    def solver_markers(self) -> np.ndarray | None:
        """The markers a solver that fills them itself is given (None for the others)."""
        return self.markers if self.fills_markers else None

    def _gather(self, a):
        return None if a is None else self.pixels.gather(a, axis=np.ndim(a) - 3)

    def frames(self, raw) -> tuple[np.ndarray, np.ndarray | None]:
        """Raw frames ``(..., H, W, C)`` -> (float32 frames ready for the solver, the saturated
        observations (bool, same shape) or None). Gathered frames have ``(1, M)`` for ``(H, W)``."""
        early = self.pixels is not None and not self.fills_here
        dark = self.dark
        full_raw = raw
        if early:
            raw, dark = self._gather(raw), self._gather(dark)
        saturated = (raw >= self.saturation) if self.saturation is not None else None
        out = self._linear(raw, dark)
        if self.pixels is not None and not early:
            out, saturated = self._gather(out), self._gather(saturated)
        if self.estimator is not None:
            out = self._without_drift(np.asarray(full_raw), out)
        return out, saturated

    def _without_drift(self, raw: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Each frame set's drift fitted on the raw frames' sampled pixels and removed from the
        prepared ``out`` (full or gathered)."""
        lead = raw.shape[:-4]
        rf = raw.reshape((-1,) + raw.shape[-4:])
        of = out.reshape((-1,) + out.shape[-4:])
        gather = None if self.pixels is None else self._gather
        res = np.empty(of.shape, np.float32)
        self.drifts = []
        for k in range(len(rf)):
            d = self.estimator.fit_raw(rf[k], self.dark)
            res[k] = d.remove_from(of[k], gather, self.shape)
            self.drifts.append(d)
        return res.reshape(lead + out.shape[-4:]) if lead else res[0]

    def reference(self, ref) -> np.ndarray | None:
        """A no-contact reference ``(P, H, W, C)`` prepared like the frames (None stays None)."""
        if ref is None:
            return None
        early = self.pixels is not None and not self.fills_here
        dark = self.dark
        if early:
            ref, dark = self._gather(ref), self._gather(dark)
        out = self._linear(ref, dark)
        return self._gather(out) if self.pixels is not None and not early else out

    def _linear(self, raw, dark) -> np.ndarray:
        out = np.asarray(raw).astype(np.float32)
        if dark is not None:
            out = out - np.asarray(dark).astype(np.float32)
        if self.fills_here:
            out = fill_markers(out, self.markers)
        return out

    def lights(self, lights):
        """``lights`` (a :class:`~pipeline.normals.lights.LightSource`) on the solved pixels."""
        return lights if self.pixels is None else lights.gathered(self.pixels)

    def finish(self, results: list) -> list:
        """The solver's results as full frames: outside the region invalid, marker pixels
        invalid (confidence 0)."""
        if self.pixels is not None:
            results = [self.pixels.scatter(r) for r in results]
        elif self.region is not None:
            from pipeline.normals.masking import PixelMask

            pm = PixelMask(self.region, self.shape, f"{self.name}: mask")
            results = [pm.restrict(r) for r in results]
        if self.estimator is not None:
            for r, d in zip(results, self.drifts):
                r.meta.update(d.result_meta())
        if self.markers is not None:
            for r in results:  # a filled-in value is a guess, not a measurement
                r.mask = r.mask & ~self.markers
                if r.confidence is not None:
                    r.confidence = np.where(self.markers, np.float32(0), r.confidence).astype(np.float32)
        return results
