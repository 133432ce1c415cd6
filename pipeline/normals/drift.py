"""Illumination drift between a press and the no-contact reference, measured where the gel is flat.

LEDs warm up, exposure and white balance wander, and a reference taken minutes before the
presses no longer matches them: every press differs from it everywhere, not only at the
contact. Left in, that difference hides the contact (the detector finds a wide, faint blob
and its edge lands tens of pixels off) and every model learns a colour shift that is not
shading. So each press's drift is fitted on its **non-contact pixels** and removed before
detection, sampling and reconstruction.

Models (:data:`DRIFT_MODELS`), per pattern-channel, ``press ~ g(x) * reference + o(x)``:

- ``none``;
- ``offset``: ``g = 1``, ``o`` a constant;
- ``gain_offset``: ``g`` and ``o`` constants (an exposure or LED brightness change);
- ``field``: ``g(x)`` and ``o(x)`` polynomials of degree ``degree`` in the image coordinates
  (a light that moved, vignetting that changed).

Optionally (``stripes=True``) a per-column offset on top (cameras whose rows are read with
column-wise offsets that change from frame to frame).

The fit is least squares over the allowed pixels (all but ``exclude``: the contact discs and
the gel bulge around them), trimmed twice: pixels whose residual exceeds ``trim`` robust
sigmas (1.4826 x MAD) are dropped and the fit repeated, so a contact that was not excluded
(the first pass of detection, before any circle is known) does not pull the fit.
:meth:`Drift.remove` maps a press onto the reference's lighting: ``(press - o - s) / g``.

Which model: ``iristac bench calibration --sensors`` measures it (docs/calibration.md, "Drift").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

__all__ = ["DRIFT_MODELS", "DRIFT_CHOICES", "AUTO_DRIFT", "GAIN_PIVOT", "SAMPLES", "LIVE_SAMPLES", "STREAM_SAMPLES", "LIVE_REFIT_EVERY", "Drift", "DriftEstimator", "contact_exclusion",
           "drift_terms", "drifted_capture", "fit_drift", "remove_drift", "resolve_drift", "check_drift"]

#: The gain is trusted as far as the reference spans more than this fraction of its own level
#: (a ridge toward 1 of that strength; see :func:`fit_drift`).
GAIN_PIVOT = 0.05

#: What :func:`fit_drift` can fit (see the module docstring).
DRIFT_MODELS = ("none", "offset", "gain_offset", "field")

#: Pixels a drift is fitted on by default (seeded sample): calibration's per-press fits and the
#: normals stage's per-frame fits.
SAMPLES = 4000

#: Pixels the live per-frame fits use (:func:`pipeline.solving.frame_solvers.frame_solver`): the fit's
#: cost grows with them (320 x 240, one loaded core: 4.7 ms for 4000, 1.3 ms for 1000, 0.8 ms for 500)
#: and a gain and an offset per channel need few (1000 moved them by 0.0002 and 0.03 DN).
LIVE_SAMPLES = 1000

#: Pixels the per-frame fits of a capture or a recording use (the normals stage, ``reconstruct``,
#: ``batch``: every frame fitted, fast and eager paths alike): as live's, since a gain and an offset
#: per channel need few (:data:`LIVE_SAMPLES`), and a recording's frames are many.
STREAM_SAMPLES = LIVE_SAMPLES

#: Live use fits the drift on every N-th frame and reuses it in between: the light drifts over
#: seconds, one fit costs about a millisecond (see :data:`LIVE_SAMPLES`) and a LUT frame at 320 x 240
#: three; so refitted, drift removal added 0.45 ms a frame to the LUT's 3.2 ms and 0.23 ms to the MLP's
#: 8.3 ms (320 x 240, one thread, load 2.1; every frame: 1.9 and 1.8 ms).
LIVE_REFIT_EVERY = 8

#: What a solve can be asked to remove (``--drift``): ``auto`` or one of :data:`DRIFT_MODELS`.
DRIFT_CHOICES = ("auto", *DRIFT_MODELS)

#: What ``auto`` removes where it applies (see :func:`resolve_drift`): on the shared GelSight test presses,
#: reconstructed with a calibration of other presses, it took the drifted capture's error back to the
#: undrifted one's and left the undrifted one's as it was (docs/reconstruction.md, "Illumination drift").
AUTO_DRIFT = "gain_offset"


def check_drift(drift: str | None, where: str = "") -> str:
    """``drift`` if it is one of :data:`DRIFT_CHOICES` (None is ``auto``), else a UserError
    naming the choices (prefixed by ``where``).

    >>> check_drift(None), check_drift("offset")
    ('auto', 'offset')
    """
    from pipeline.base.errors import UserError

    d = "auto" if drift is None else str(drift)
    if d not in DRIFT_CHOICES:
        raise UserError(f"{where + ': ' if where else ''}--drift must be one of {', '.join(DRIFT_CHOICES)}, got {d!r}")
    return d


def resolve_drift(drift: str | None, *, applies: bool, has_reference: bool, where: str = "frames") -> str:
    """The drift model a solve removes: ``drift`` (one of :data:`DRIFT_CHOICES`; None is ``auto``).

    ``auto`` is :data:`AUTO_DRIFT` where it ``applies`` (the solver keys on the no-contact
    reference: a calibration's model, the ratio to the reference, the contact mask) and a reference
    exists, else ``none``. A model asked for by name needs a reference (it is what the frames are
    mapped onto).

    Examples
    --------
    >>> resolve_drift("auto", applies=True, has_reference=True), resolve_drift(None, applies=False, has_reference=True)
    ('gain_offset', 'none')
    >>> resolve_drift("offset", applies=False, has_reference=False, where="cap.h5")
    Traceback (most recent call last):
    ...
    pipeline.base.errors.UserError: cap.h5: --drift offset maps the frames onto the no-contact reference's lighting; \
there is no reference (the capture has none, and the solver's model stores none): use --drift none
    """
    from pipeline.base.errors import UserError

    d = check_drift(drift, where)
    if d == "auto":
        return AUTO_DRIFT if applies and has_reference else "none"
    if d != "none" and not has_reference:
        raise UserError(f"{where}: --drift {d} maps the frames onto the no-contact reference's lighting; there is no "
                        f"reference (the capture has none, and the solver's model stores none): use --drift none")
    return d


def drift_terms(shape: tuple[int, int], degree: int) -> np.ndarray:
    """Monomials ``u^i v^j`` (``i + j <= degree``) of the image coordinates scaled to [-1, 1]: ``(T, H, W)``
    (read-only: computed once per shape and degree).

    Examples
    --------
    >>> drift_terms((3, 5), 1).shape, drift_terms((3, 5), 2).shape
    ((3, 3, 5), (6, 3, 5))
    >>> drift_terms((3, 5), 0)[0].tolist() == np.ones((3, 5)).tolist()
    True
    """
    return _terms(int(shape[0]), int(shape[1]), int(degree))


@lru_cache(maxsize=16)
def _terms(h: int, w: int, degree: int) -> np.ndarray:
    v, u = np.meshgrid(np.linspace(-1.0, 1.0, h), np.linspace(-1.0, 1.0, w), indexing="ij")
    out = np.stack([u ** i * v ** j for i in range(degree + 1) for j in range(degree + 1 - i)])
    out.flags.writeable = False
    return out


def _terms_at(shape: tuple[int, int], degree: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """:func:`drift_terms` at the pixels ``(rows, cols)`` only: ``(T, N)``, the same values."""
    h, w = int(shape[0]), int(shape[1])
    v, u = np.linspace(-1.0, 1.0, h)[rows], np.linspace(-1.0, 1.0, w)[cols]
    return np.stack([u ** i * v ** j for i in range(degree + 1) for j in range(degree + 1 - i)])


@dataclass
class Drift:
    """A fitted drift of one press (``(P, H, W, C)``) against the reference.

    Attributes
    ----------
    model : str
        One of :data:`DRIFT_MODELS`.
    gain, offset : ndarray, shape (P, C, T)
        Polynomial coefficients of ``g`` and ``o`` over :func:`drift_terms` (T = 1 for the
        constant models).
    degree : int
    stripes : ndarray, shape (P, C, W), or None
        Per-column offsets.
    residual_dn : float
        RMS residual of the fitted pixels after the last trim (the drift the model cannot explain).
    before_dn : float
        RMS of ``press - reference`` over the same pixels (the drift before removal).
    pixels : int
        Pixels fitted (after trimming).
    """

    model: str
    gain: np.ndarray
    offset: np.ndarray
    degree: int = 0
    stripes: np.ndarray | None = None
    residual_dn: float = 0.0
    before_dn: float = 0.0
    pixels: int = 0
    meta: dict[str, Any] = field(default_factory=dict)

    def fields(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """``g`` and ``o`` as ``(P, H, W, C)`` (stripes folded into ``o``)."""
        t = drift_terms(shape, self.degree)
        g = np.einsum("pct,thw->phwc", self.gain, t)
        o = np.einsum("pct,thw->phwc", self.offset, t)
        if self.stripes is not None:
            o = o + self.stripes.transpose(0, 2, 1)[:, None, :, :]
        return g, o

    def remove(self, press: np.ndarray) -> np.ndarray:
        """``press (P, H, W, C)`` mapped onto the reference's lighting, float32
        (:meth:`remove_from` of the whole image: a constant drift without building fields)."""
        return self.remove_from(press)

    @property
    def constant(self) -> bool:
        """Whether ``g`` and ``o`` are constants per pattern-channel (no field, no stripes)."""
        return self.degree == 0 and self.stripes is None

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """A constant drift's ``(g, o)`` per pattern-channel, ``(P * C,)`` float64 each (pattern-major,
        channel-minor: the solvers' order), ``g`` already safe to divide by (as :meth:`remove`)."""
        if not self.constant:
            raise ValueError(f"Drift.coefficients: the {self.model!r} drift varies over the image (degree "
                             f"{self.degree}{', stripes' if self.stripes is not None else ''})")
        g = self.gain[..., 0].reshape(-1)
        return np.where(np.abs(g) > 1e-3, g, 1.0), self.offset[..., 0].reshape(-1).astype(np.float64)

    def remove_from(self, frames: np.ndarray, gather=None, shape: tuple[int, int] | None = None) -> np.ndarray:
        """:meth:`remove` of frames ``(P, H, W, C)``, or of a region's pixels ``(P, 1, M, C)``:
        ``gather`` maps a full ``(P, H, W, C)`` field of the image ``shape (H, W)`` onto them (a
        varying drift needs both). Float64 arithmetic, float32 result.

        Examples
        --------
        >>> d = Drift("gain_offset", np.full((1, 3, 1), 2.0), np.full((1, 3, 1), 10.0))
        >>> d.remove_from(np.full((1, 1, 4, 3), 30.0))[0, 0, 0].tolist(), d.coefficients()[0].tolist()
        ([10.0, 10.0, 10.0], [2.0, 2.0, 2.0])
        """
        f = np.asarray(frames, np.float32)
        if self.model == "none":
            return f
        if self.constant:
            p, c = self.gain.shape[:2]
            g, o = (a.reshape(p, 1, 1, c) for a in self.coefficients())
        else:
            if gather is not None and shape is None:
                raise ValueError("Drift.remove_from: a gathered region needs the image shape for a varying drift")
            g, o = self.fields(tuple(shape) if gather is not None else f.shape[1:3])
            g = np.where(np.abs(g) > 1e-3, g, 1.0)
            if gather is not None:
                g, o = gather(g), gather(o)
        return ((f - o) / g).astype(np.float32)

    def result_meta(self) -> dict[str, Any]:
        """What a normals result records of the drift removed from its frames."""
        return {"drift": self.model, "drift_before_dn": round(self.before_dn, 3),
                "drift_residual_dn": round(self.residual_dn, 3)}

    def summary(self) -> dict[str, Any]:
        """JSON-ready: model, mean gain and offset per pattern-channel, residual before and after."""
        return {"model": self.model, "gain": np.round(self.gain[..., 0], 4).tolist(),
                "offset_dn": np.round(self.offset[..., 0], 2).tolist(), "before_dn": round(self.before_dn, 3),
                "residual_dn": round(self.residual_dn, 3), "pixels": int(self.pixels)}


def _design(model: str, ref: np.ndarray, terms: np.ndarray) -> np.ndarray:
    """``(M, N, K)`` columns of the linear drift model at N pixels (ref ``(M, N)``, terms ``(T, N)``)."""
    m, n = ref.shape
    if model == "offset":
        return np.ones((m, n, 1))
    tt = np.broadcast_to(terms.T[None], (m, n, terms.shape[0]))
    return np.concatenate([ref[..., None] * tt, tt], axis=2)


def _lstsq_batched(A: np.ndarray, y: np.ndarray, w: np.ndarray, ridge: np.ndarray | None = None,
                   prior: np.ndarray | None = None) -> np.ndarray:
    """Per system m: least squares of ``A[m] (N, K) x = y[m]`` over the rows where ``w[m]``, plus
    ``ridge[m] * |x - prior|^2`` on the coefficients where ``prior`` is not NaN."""
    # Batched matmuls, not einsum: BLAS per system, about 10x faster at these sizes (einsum
    # without a contraction path loops in C); the same sums to rounding (1e-15 relative).
    Awt = (A * w[..., None]).transpose(0, 2, 1)
    G = Awt @ A
    b = (Awt @ y[..., None])[..., 0]
    k = A.shape[2]
    if ridge is not None and prior is not None:
        on = np.isfinite(prior).astype(np.float64)
        G = G + ridge[:, None, None] * np.eye(k) * on[None, :, None]
        b = b + ridge[:, None] * np.nan_to_num(prior)[None, :]
    G = G + 1e-9 * np.trace(G, axis1=1, axis2=2)[:, None, None] / k * np.eye(k)
    return np.linalg.solve(G, b[..., None])[..., 0]


def fit_drift(press: np.ndarray, reference: np.ndarray, exclude: np.ndarray | None = None, *,
              model: str = "gain_offset", degree: int = 2, stripes: bool = False, trim: float = 3.0,
              max_samples: int = SAMPLES, seed: int = 0) -> Drift:
    """Fit the drift of one press against the reference on its non-contact pixels.

    Parameters
    ----------
    press, reference : ndarray, shape (P, H, W, C)
        Linear values.
    exclude : ndarray, shape (H, W), bool, optional
        Pixels not fitted (the contact and the bulge around it, markers). None: every pixel,
        the trimming alone keeps a contact out.
    model : {"none", "offset", "gain_offset", "field"}
    degree : int
        Polynomial degree of ``g`` and ``o`` for ``field``.
    stripes : bool
        Also fit a per-column offset (median of the residual down each column).
    trim : float
        Residuals beyond this many robust sigmas are dropped and the fit repeated (twice).
        The gain terms carry a ridge toward 1 worth one pseudo-observation per pixel at
        :data:`GAIN_PIVOT` times the mean reference level from it: a reference with little
        spread (a far-field lit gel) leaves the drift an offset.
    max_samples : int
        Pixels drawn (seeded) for the fit; the stripes use every allowed pixel. A gain and an
        offset per pattern-channel need few: 4000 (20000 moved the gains of the shared GelSight
        frames by less than 1 % and took seven times as long).

    Returns
    -------
    Drift

    Examples
    --------
    A press 10 % brighter and 5 DN up everywhere, with a bright contact in one corner:

    >>> rng = np.random.default_rng(0)
    >>> ref = rng.uniform(50, 150, (1, 40, 50, 3))
    >>> press = 1.1 * ref + 5.0; press[0, :10, :10] += 80
    >>> d = fit_drift(press, ref)
    >>> np.round(d.gain[0, :, 0], 2).tolist(), np.round(d.offset[0, :, 0]).tolist()
    ([1.1, 1.1, 1.1], [5.0, 5.0, 5.0])
    >>> float(np.abs(d.remove(press) - ref)[0, 20:, 20:].max()) < 0.2  # the ridge's pull toward gain 1
    True

    On a reference of one level the gain cannot be told from an offset: the drift stays an offset.

    >>> flat = np.full((1, 40, 50, 3), 100.0) + rng.normal(0, 1, (1, 40, 50, 3))
    >>> d = fit_drift(flat + 12.0 + rng.normal(0, 1, flat.shape), flat)
    >>> round(float(d.gain[0, 0, 0]), 2), round(float(d.offset[0, 0, 0]))
    (1.0, 12)
    """
    press = np.asarray(press)
    if press.ndim != 4 or press.shape != np.shape(reference):
        raise ValueError(f"fit_drift: press and reference must both be (P, H, W, C), got {press.shape} and "
                         f"{np.shape(reference)}")
    est = DriftEstimator(reference, exclude, model=model, degree=degree, trim=trim, max_samples=max_samples, seed=seed)
    return est.fit(press, stripes=stripes)


class DriftEstimator:
    """The drift of frame sets against one reference, fitted on a fixed sample of its pixels.

    What :func:`fit_drift` does, split in two: what depends on the reference alone (the
    allowed pixels, the seeded sample of them, the reference's values there, the design of the
    linear model) is built once here; :meth:`fit` (linear frames) or :meth:`fit_raw` (integer
    camera frames and a dark level: only the sampled pixels are converted) fits one frame set.
    That is what the normals stage (:class:`pipeline.normals.prepare.FramePrep`) and the live
    fast paths (:mod:`pipeline.normals.fast_models`) use per frame: with no contact known,
    ``exclude`` holds only the pixels never to fit (markers, outside the solved region) and
    the trimming keeps a contact out.

    Parameters
    ----------
    reference : ndarray, shape (P, H, W, C)
        The no-contact reference, linear (dark level removed).
    exclude, model, degree, trim, max_samples, seed
        As :func:`fit_drift`.
    refit_every : int
        :meth:`fit_raw` fits on every N-th call, returning the last fit in between (live use:
        :data:`LIVE_REFIT_EVERY`).

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> ref = rng.uniform(40, 200, (1, 30, 40, 3))
    >>> est = DriftEstimator(ref)
    >>> raw = np.clip(np.round(0.9 * ref + 12), 0, 255).astype(np.uint8); raw[0, 5:12, 5:12] = 255
    >>> d = est.fit_raw(raw)
    >>> np.round(d.gain[0, :, 0], 2).tolist(), np.round(d.offset[0, :, 0]).tolist()
    ([0.9, 0.9, 0.9], [12.0, 12.0, 12.0])
    """

    def __init__(self, reference: np.ndarray, exclude: np.ndarray | None = None, *, model: str = "gain_offset",
                 degree: int = 2, trim: float = 3.0, max_samples: int = SAMPLES, seed: int = 0, refit_every: int = 1):
        reference = np.asarray(reference)
        self.refit_every = max(1, int(refit_every))
        self.calls, self.last = 0, None
        if reference.ndim != 4:
            raise ValueError(f"DriftEstimator: the reference must be (P, H, W, C), got {reference.shape}")
        if model not in DRIFT_MODELS:
            raise ValueError(f"fit_drift: model must be one of {', '.join(DRIFT_MODELS)}, got {model!r}")
        p, h, w, c = reference.shape
        self.reference, self.model, self.trim = reference, model, float(trim)
        self.degree = degree if model == "field" else 0
        self.terms_count = (self.degree + 1) * (self.degree + 2) // 2
        if exclude is not None and np.shape(exclude) != (h, w):
            raise ValueError(f"DriftEstimator: exclude must be (H, W) = {(h, w)} like the reference, got "
                             f"{np.shape(exclude)}")
        self.allowed = np.ones((h, w), bool) if exclude is None else ~np.asarray(exclude, bool)
        rr, cc = np.nonzero(self.allowed)
        self.available = len(rr)
        if len(rr) > max_samples:
            pick = np.random.default_rng(seed).choice(len(rr), max_samples, replace=False)
            rr, cc = rr[pick], cc[pick]
        self.rows, self.cols = rr, cc
        self.x = self.samples(reference)  # (M, N)
        nt = self.terms_count
        self.A = None if model == "none" else _design(model, self.x, _terms_at((h, w), self.degree, rr, cc))
        self.prior = None if model in ("none", "offset") else np.r_[1.0, np.zeros(nt - 1), np.full(nt, np.nan)]

    @property
    def enough(self) -> bool:
        """Whether enough pixels are allowed to fit the model at all."""
        return self.available >= 4 * self.terms_count + 8

    def samples(self, frames: np.ndarray, dark: np.ndarray | None = None) -> np.ndarray:
        """The sampled pixels of ``frames (P, H, W, C)`` as float64 ``(P * C, N)`` (minus ``dark (H, W, C)``
        in float32 first, as :class:`pipeline.normals.prepare.FramePrep` subtracts it)."""
        f = np.asarray(frames)
        p, c = f.shape[0], f.shape[-1]
        v = f[:, self.rows, self.cols, :]
        if dark is not None:
            v = v.astype(np.float32) - np.asarray(dark)[self.rows, self.cols, :].astype(np.float32)
        return v.astype(np.float64).transpose(0, 2, 1).reshape(p * c, -1)

    def _identity(self) -> Drift:
        p, c = self.reference.shape[0], self.reference.shape[3]
        nt = self.terms_count
        ident = Drift(self.model, np.zeros((p, c, nt)), np.zeros((p, c, nt)), self.degree)
        ident.gain[..., 0] = 1.0
        return ident

    def fit(self, press: np.ndarray, *, stripes: bool = False) -> Drift:
        """The drift of one linear frame set ``press (P, H, W, C)`` (see :func:`fit_drift`)."""
        press = np.asarray(press)
        if press.shape != self.reference.shape:
            raise ValueError(f"fit_drift: press and reference must both be (P, H, W, C), got {press.shape} and "
                             f"{self.reference.shape}")
        if not self.enough:
            return self._fit_samples(None)
        out = self._fit_samples(self.samples(press))
        if stripes and out.model != "none":
            out.stripes = _column_offsets(np.asarray(press, np.float64), np.asarray(self.reference, np.float64), out,
                                          self.allowed)
        return out

    def fit_raw(self, raw: np.ndarray, dark: np.ndarray | None = None) -> Drift:
        """The drift of one camera frame set ``raw (P, H, W, C)`` (any dtype) minus ``dark``; only
        the sampled pixels are read. With ``refit_every`` N > 1 (a stream: the light drifts over
        seconds), fitted on every N-th call and the last fit returned in between (:meth:`reset`
        starts over)."""
        raw = np.asarray(raw)
        if raw.shape != self.reference.shape:
            raise ValueError(f"DriftEstimator: frames must be {self.reference.shape} like the reference, got "
                             f"{raw.shape}")
        if self.refit_every == 1:  # fitted every call: nothing shared, so threads may fit frames at once
            return self._fit_samples(self.samples(raw, dark) if self.enough else None)
        due = self.last is None or self.calls % self.refit_every == 0
        self.calls += 1
        if due:
            self.last = self._fit_samples(self.samples(raw, dark) if self.enough else None)
        return self.last

    def reset(self) -> None:
        """Forget the last fit: the next :meth:`fit_raw` fits (after a warm-up frame, a new stream)."""
        self.calls, self.last = 0, None

    def _fit_samples(self, y: np.ndarray | None) -> Drift:
        """The drift from the frame set's sampled values ``y (M, N)``."""
        ident = self._identity()
        if y is None:
            ident.meta["note"] = f"only {self.available} pixels outside the contacts: drift not fitted"
            return ident
        x, A, model, nt = self.x, self.A, self.model, self.terms_count
        p, c = self.reference.shape[0], self.reference.shape[3]
        ident.before_dn = float(np.sqrt(np.mean((y - x) ** 2)))
        if A is None:  # the "none" model
            ident.residual_dn, ident.pixels = ident.before_dn, y.shape[1]
            return ident
        if model in ("offset", "gain_offset") and nt == 1:  # one compiled pass (pipeline.normals._drift_kernel)
            from pipeline.normals._drift_kernel import fit_constant

            g, o, res, keep = fit_constant(np.ascontiguousarray(x, np.float64), np.ascontiguousarray(y, np.float64),
                                           model == "gain_offset", float(self.trim), float(GAIN_PIVOT))
            return Drift(model, g.reshape(p, c, 1), o.reshape(p, c, 1), self.degree,
                         residual_dn=float(np.sqrt(np.mean(res[keep] ** 2))), before_dn=ident.before_dn,
                         pixels=int(keep.all(axis=0).sum()))
        return self._fit_numpy(y, ident)

    def _fit_numpy(self, y: np.ndarray, ident: Drift) -> Drift:
        """:meth:`_fit_samples` with numpy: every model (the reference the constant models' kernel
        is checked against)."""
        x, A, model, nt = self.x, self.A, self.model, self.terms_count
        p, c = self.reference.shape[0], self.reference.shape[3]
        keep = np.ones(y.shape, bool)
        target = y - x if model == "offset" else y
        # The gain is pulled toward 1 as far as the reference lacks spread: a gain is told from an
        # offset only by how the drift changes with the reference's level, and on a reference of
        # nearly one level (a far-field lit gel) it would be a guess that the contacts' colours,
        # far from that level, would pay for.
        prior = self.prior
        floor = 1e-3 * np.median(np.abs(target), axis=1, keepdims=True) + 1e-9  # noise-free frames
        for _ in range(3):
            ridge = None if prior is None else \
                keep.sum(axis=1) * (GAIN_PIVOT * np.abs((x * keep).sum(axis=1)) / np.maximum(keep.sum(axis=1), 1)) ** 2
            coef = _lstsq_batched(A, target, keep.astype(np.float64), ridge, prior)
            res = target - (A @ coef[..., None])[..., 0]
            dev = np.abs(res - np.median(res, axis=1, keepdims=True))
            sig = 1.4826 * np.median(dev, axis=1, keepdims=True)
            keep = dev <= self.trim * np.maximum(sig, floor)
            keep[keep.sum(axis=1) < 2 * A.shape[2] + 2] = True
        if model == "offset":
            gain, offset = np.ones((p * c, 1)), coef
        else:
            gain, offset = coef[:, :nt], coef[:, nt:]
        return Drift(model, gain.reshape(p, c, nt), offset.reshape(p, c, nt), self.degree,
                     residual_dn=float(np.sqrt(np.mean(res[keep] ** 2))), before_dn=ident.before_dn,
                     pixels=int(keep.all(axis=0).sum()))


def _column_offsets(press, reference, drift: Drift, allowed: np.ndarray) -> np.ndarray:
    """Median residual down each column (allowed pixels only) per pattern-channel: ``(P, C, W)``."""
    g, o = drift.fields(press.shape[1:3])
    res = np.where(allowed[None, :, :, None], press - (g * reference + o), np.nan)
    with np.errstate(all="ignore"):
        col = np.nanmedian(res, axis=1)  # (P, W, C)
    return np.nan_to_num(col).transpose(0, 2, 1)


def contact_exclusion(shape: tuple[int, int], center_xy, radius_px: float, ball_radius_px: float,
                      factor: float = 1.5) -> np.ndarray:
    """Pixels ``(H, W)`` a contact disturbs: within ``factor x`` its radius plus a quarter of the ball radius.

    The gel bulges and is pulled around a contact; the margin keeps that out of the drift fit.

    Examples
    --------
    >>> m = contact_exclusion((20, 30), (15.0, 10.0), 4.0, 8.0)
    >>> bool(m[10, 15]), bool(m[10, 23]), bool(m[0, 0])
    (True, True, False)
    """
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    r = factor * max(float(radius_px), 0.2 * ball_radius_px) + 0.25 * ball_radius_px
    return np.hypot(xx - center_xy[0], yy - center_xy[1]) <= r


def remove_drift(frames: np.ndarray, reference: np.ndarray, circles, ball_radius_px: float, *,
                 model: str = "gain_offset", degree: int = 2, stripes: bool = False,
                 exclude: np.ndarray | None = None) -> tuple[np.ndarray, list[Drift]]:
    """Every press of ``frames (K, P, H, W, C)`` mapped onto the reference's lighting.

    Each press's drift is fitted outside its contact (:func:`contact_exclusion` around its
    circle, accepted or not: a rejected circle still marks where the press differs) and
    ``exclude`` (markers).

    Returns
    -------
    corrected : ndarray, float32, shape (K, P, H, W, C)
    drifts : list of Drift
    """
    frames = np.asarray(frames, np.float32)
    if frames.ndim != 5:
        raise ValueError(f"remove_drift: frames must be (K, P, H, W, C), got {frames.shape}")
    out = np.empty_like(frames)
    drifts = []
    for k, circ in enumerate(circles):
        ex = None if exclude is None else np.asarray(exclude, bool).copy()
        if circ is not None and circ.radius_px > 0:
            m = contact_exclusion(frames.shape[2:4], circ.center_xy, circ.radius_px, ball_radius_px)
            ex = m if ex is None else ex | m
        d = fit_drift(frames[k], reference, ex, model=model, degree=degree, stripes=stripes)
        out[k] = d.remove(frames[k])
        drifts.append(d)
    return out, drifts


def drifted_capture(cap, seed: int = 0, max_gain: float = 0.15, max_offset_dn: float = 30.0):
    """``cap`` (a :class:`pipeline.base.capture.Capture`) with every press drifted against its untouched
    reference, for tests and benchmarks: per press, pattern and channel a gain in ``1 +- max_gain`` and an
    offset in ``+-max_offset_dn`` (seeded, uniform), rounded and clipped to the frames' integer range.

    Examples
    --------
    >>> from pipeline.base.capture import Capture
    >>> cap = Capture(frames=np.full((2, 1, 4, 4, 3), 100, np.uint8), reference=np.full((1, 4, 4, 3), 100, np.uint8),
    ...               drive=np.eye(3, dtype=np.float32)[None], brightness=np.ones(1, np.float32), mm_per_px=0.1)
    >>> d = drifted_capture(cap)
    >>> d.frames.dtype.name, bool((d.reference == cap.reference).all()), int(np.abs(d.frames.astype(int) - 100).max()) <= 45
    ('uint8', True, True)
    """
    from pipeline.base.capture import Capture

    frames = np.asarray(cap.frames)
    rng = np.random.default_rng(seed)
    k, p = frames.shape[:2]
    c = frames.shape[-1]
    gain = 1.0 + rng.uniform(-max_gain, max_gain, (k, p, 1, 1, c))
    offset = rng.uniform(-max_offset_dn, max_offset_dn, (k, p, 1, 1, c))
    out = np.round(frames.astype(np.float64) * gain + offset)
    if frames.dtype.kind in "ui":
        info = np.iinfo(frames.dtype)
        out = np.clip(out, info.min, info.max)
    return Capture(frames=out.astype(frames.dtype), reference=cap.reference, drive=cap.drive,
                   brightness=cap.brightness, mm_per_px=cap.mm_per_px, dark=cap.dark, labels=cap.labels,
                   meta=dict(cap.meta), markers=cap.markers)
