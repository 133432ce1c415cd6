"""Live paths of the learned single-frame models: a vectorised lookup table and a fused MLP.

Both take the model's arrays (built from a calibration by :mod:`pipeline.solving.frame_solvers`;
this layer knows no calibration object), precompute what depends only on the pixel and the
session's reference, and turn an integer camera frame into normals, mask and confidence in
one compiled pass. The eager references are the models' own ``normal_maps``
(:mod:`calibration.normal_maps`); ``tests/pipeline/normals/test_fast_paths.py`` pins the
agreement:

- :class:`FastLUT`: the lookup table with its per-bin position correction
  (``g = sum_t c_t(bin(d)) phi_t(u, v)``), evaluated in float64 exactly as the model does
  (same bin arithmetic, same polynomial terms, precomputed once per pixel), then the model's
  tilt gain and clip; agreement to the last bit of float32 but for libm rounding.
- :class:`FastMLP`: the network evaluated per block of pixels in float32 with the layers
  fused (the block's activations stay in the L1 cache). The first layer's input is the colour
  change, the reference colour and the position; only the change varies between frames, so
  the rest of the first layer (``W_r r(x) + W_uv (u, v) + b``) is precomputed per pixel.
  SiLU uses a vectorisable rational tanh (Eigen's, within 4e-7), so the result agrees with
  torch's to about 1e-6.

Both remove the frame's illumination drift against the reference when given a
:class:`~pipeline.normals.drift.DriftEstimator` (``drift=``, what
:meth:`pipeline.normals.prepare.FramePrep.use_drift` built): the drift is fitted on the
estimator's sampled pixels of the integer frame (a few thousand of them: the same values the
eager path fits, so the same drift), and its per-channel gain and offset are applied inside the
kernel, ``v' = (v - o) / g`` in float64 as :meth:`~pipeline.normals.drift.Drift.remove` does (as a
product with ``1 / g``: the same float32 result but in one case in a billion).
A drift that varies over the image (``field``) is the eager path's.

Numba, compiled once and cached on disk (``cache=True``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from pipeline.normals.fast import blocked, frame_planes_np, run_split

__all__ = ["FastLUT", "FastMLP", "finish_normals"]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _finish_one(a, b, c, ok, apply, gain, limit):  # pragma: no cover - compiled
    """One pixel of the models' output correction and ``predict_normal_maps``'s checks
    (see :func:`finish_normals`); returns ``(n_x, n_y, n_z, valid)``."""
    if apply:
        a *= gain
        b *= gain
        mag = np.sqrt(a * a + b * b)  # np.hypot's libm call is 10x slower; equal to 1 ulp here
        if mag > limit:
            f = limit / max(mag, 1e-12)
            a *= f
            b *= f
        c = np.sqrt(min(max(1.0 - (a * a + b * b), 0.0), 1.0))
    good = ok and np.isfinite(a) and np.isfinite(b) and np.isfinite(c)
    nrm = np.sqrt(a * a + b * b + c * c) if good else 0.0
    good = good and nrm > 0.5
    if good:
        s = max(nrm, 1e-12)
        return a / s, b / s, c / s, True
    return 0.0, 0.0, 1.0, False


@njit(cache=True, nogil=True, error_model="numpy")
def _lut_kernel(obs, dark, ref, lo, width, bins, filled, support, table, coef, phi, apply, gain, limit, drift_g,
                drift_o, start, stop, normals, mask, conf):  # pragma: no cover - compiled
    """Pixels ``start:stop``: colour change ``d = (I - dark) - ref`` (float32, as the model's
    samples; with a drift, ``I - dark`` is first mapped to ``((I - dark) - drift_o) * drift_g``
    per channel in float64 when ``drift_g``, the drift's inverse gain, is not empty), bin ``floor((d - lo) / width * bins)`` in float64, gradient from the table (or
    the bin's position polynomial ``coef`` when ``coef`` is not empty), the normal
    ``(-g_x, -g_y, 1) / |.|`` (``pipeline.base.frames.gradients_to_normals``), the output
    correction (:func:`_finish_one`), confidence ``support / (support + 1)``; all in float64
    like the model, written as float32."""
    T = phi.shape[1]
    has_dark = dark.shape[0] > 0
    has_drift = drift_g.shape[0] > 0
    use_coef = coef.shape[0] > 0
    for x in range(start, stop):
        inside = True
        i0 = 0
        i1 = 0
        i2 = 0
        for c in range(3):
            v = np.float32(obs[c, x])
            if has_dark:
                v = v - dark[c, x]
            if has_drift:
                v = np.float32((np.float64(v) - drift_o[c]) * drift_g[c])
            d = np.float64(v - ref[c, x])
            t = (d - lo[c]) / width[c] * bins
            i = int(np.floor(t))
            if i < 0 or i >= bins:
                inside = False
            i = min(max(i, 0), bins - 1)
            if c == 0:
                i0 = i
            elif c == 1:
                i1 = i
            else:
                i2 = i
        valid = inside and filled[i0, i1, i2]
        gx = 0.0
        gy = 0.0
        cf = np.float32(0.0)
        if valid:
            sup = support[i0, i1, i2]
            cf = sup / (sup + np.float32(1.0))
            if use_coef:
                for t_ in range(T):
                    gx += phi[x, t_] * coef[i0, i1, i2, t_, 0]
                    gy += phi[x, t_] * coef[i0, i1, i2, t_, 1]
            else:
                gx = np.float64(table[i0, i1, i2, 0])
                gy = np.float64(table[i0, i1, i2, 1])
        a = 0.0 - gx
        b = 0.0 - gy
        n = np.sqrt(a * a + b * b + 1.0)
        n0, n1, n2, good = _finish_one(a / n, b / n, 1.0 / n, valid, apply, gain, limit)
        normals[x, 0] = n0
        normals[x, 1] = n1
        normals[x, 2] = n2
        mask[x] = good
        conf[x] = min(max(cf, np.float32(0.0)), np.float32(1.0)) if good else np.float32(0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def finish_normals(nx, ny, nz, ok, apply, gain, limit, normals, mask):  # pragma: no cover - compiled
    """The models' output correction (``calibration.models.base.scale_tilt``: tilt ``(n_x, n_y)``
    times ``gain``, clipped to ``max_tilt``, never above 0.999) and ``predict_normal_maps``'s
    checks (finite, norm above 0.5, renormalised), in float64; flat ``(0, 0, 1)`` where invalid."""
    for x in range(nx.shape[0]):
        n0, n1, n2, good = _finish_one(nx[x], ny[x], nz[x], ok[x], apply, gain, limit)
        normals[x, 0] = n0
        normals[x, 1] = n1
        normals[x, 2] = n2
        mask[x] = good


class _Base:
    """What both models share: the frame size, the marker mask, the tilt correction."""

    def __init__(self, shape, reference, tilt_gain: float, max_tilt, markers, drift=None, dark=None):
        self.shape = (int(shape[0]), int(shape[1]))
        self.drift, self.dark_hwc = drift, None if dark is None else np.asarray(dark, np.float32)
        self.last_drift = None
        #: What the confidence measures (the model's own words, ``meta["confidence"]`` of the eager path).
        self.confidence_meaning: str | None = None
        self.gain = float(tilt_gain)
        self.limit = 0.999 if max_tilt is None else min(float(max_tilt), 0.999)
        self.apply_tilt = self.gain != 1.0 or max_tilt is not None  # as CalibrationModel.predict_with_confidence
        ref = np.asarray(reference, np.float32)
        H, W = self.shape
        if ref.ndim != 4 or ref.shape[1:3] != (H, W):
            raise ValueError(f"{type(self).__name__}: reference must be (P, {H}, {W}, C), got {ref.shape}")
        self.num_patterns, self.channels = ref.shape[0], ref.shape[3]
        self.markers = None if markers is None else np.asarray(markers, bool)
        if self.markers is not None:
            from pipeline.base.errors import UserError

            # Filling markers in (OpenCV inpainting) costs more than the model; the live path
            # does not do it: the eager solver does.
            raise UserError("the fast path does not fill in printed markers; use the eager solver (markers given)")
        if drift is not None and drift.model not in ("none", "offset", "gain_offset"):
            raise ValueError(f"{type(self).__name__}: the fast path removes a constant drift per channel; "
                             f"{drift.model!r} varies over the image (the eager solver removes it)")

    def reset_drift(self) -> None:
        """The next frame's drift is fitted afresh (after a warm-up frame)."""
        if self.drift is not None:
            self.drift.reset()

    def _drift_planes(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, Any]:
        """The frame's drift (gain, offset) per pattern-channel for the kernel, fitted by the
        estimator on its sampled pixels, and the drift itself; empty arrays and None without an
        estimator (the kernel skips it). Several threads may solve frames at once: nothing here
        is kept between frames but :attr:`last_drift`, a report."""
        if self.drift is None or self.drift.model == "none":
            return np.zeros(0), np.zeros(0), None
        d = self.drift.fit_raw(frames, self.dark_hwc)
        self.last_drift = d
        g, o = d.coefficients()
        # The kernels multiply by 1 / g: within an ulp of float64 of dividing (as Drift.remove does),
        # which the float32 result absorbs, and a division per value cost 40 % of the LUT's time.
        return np.ascontiguousarray(1.0 / g, np.float64), np.ascontiguousarray(o, np.float64), d

    def _meta(self, solver: str, drift=None) -> dict:
        meta = {"solver": solver, "method": "fast"}
        if self.confidence_meaning:
            meta["confidence"] = self.confidence_meaning
        if drift is not None and self.drift is not None and self.drift.model != "none":
            meta.update(drift.result_meta())
        return meta

    def _check(self, frames) -> np.ndarray:
        f = np.asarray(frames)
        P, (H, W), C = self.num_patterns, self.shape, self.channels
        if f.ndim == 3:
            f = f[None]
        if f.shape != (P, H, W, C):
            raise ValueError(f"{type(self).__name__}.solve: frames must be ({P}, {H}, {W}, {C}), got {f.shape}")
        if f.dtype.kind not in "ui":
            raise ValueError(f"{type(self).__name__}.solve: integer frames expected (uint8/uint16), got {f.dtype}")
        return f

    def _result(self, normals, mask, conf, meta):
        from pipeline.normals.result import NormalResult

        H, W = self.shape
        m = mask.reshape(H, W)
        return NormalResult(normals=normals.reshape(H, W, 3), albedo=m[..., None].astype(np.float32),
                            residual=np.zeros((H, W), np.float32), condition=np.ones((H, W), np.float32), mask=m,
                            count=np.where(m, self.num_patterns * self.channels, 0).astype(np.int32), meta=meta,
                            confidence=conf.reshape(H, W))


class FastLUT(_Base):
    """A calibration's lookup table (and per-bin position correction) as one compiled pass.

    Parameters
    ----------
    lo, hi : ndarray, shape (3,)
        Colour-change range of the bins (``LookupTable.lo``, ``.hi``).
    table : ndarray, shape (B, B, B, 2)
        Gradient per bin.
    filled, support : ndarray, shape (B, B, B)
        Bins with a value; smoothed sample count per bin.
    reference : ndarray, shape (1, H, W, 3)
        The no-contact frame (dark level removed) changes are taken against.
    coef : ndarray, shape (B, B, B, T, 2), optional
        Per-bin position polynomial (``LUTModel.position_coef``) ...
    phi : ndarray, shape (H * W, T), optional
        ... and its terms at every pixel (``poly_terms`` of the model), float64.
    tilt_gain, max_tilt : float
        The model's output correction.
    dark : ndarray, shape (H, W, 3), optional
        Subtracted from every frame first.
    drift : DriftEstimator, optional
        Against ``reference``: each frame's drift removed (see the module docstring).
    """

    def __init__(self, lo, hi, table, filled, support, reference, *, coef=None, phi=None, tilt_gain: float = 1.0,
                 max_tilt=None, dark=None, markers=None, drift=None):
        super().__init__(np.asarray(reference).shape[1:3], reference, tilt_gain, max_tilt, markers, drift, dark)
        if (self.num_patterns, self.channels) != (1, 3):
            raise ValueError(f"FastLUT: one RGB pattern expected, the reference is {np.asarray(reference).shape}")
        H, W = self.shape
        self.lo = np.asarray(lo, np.float64)
        self.width = np.maximum(np.asarray(hi, np.float64) - self.lo, 1e-9)
        self.table = np.ascontiguousarray(table, np.float32)
        self.bins = int(self.table.shape[0])
        self.filled = np.ascontiguousarray(filled, np.bool_)
        self.support = np.ascontiguousarray(support, np.float32)
        self.ref = frame_planes_np(np.asarray(reference, np.float32))  # (3, M)
        if coef is None:
            self.coef = np.zeros((0, 0, 0, 0, 2))
            self.phi = np.zeros((H * W, 0))
        else:
            self.coef = np.ascontiguousarray(coef, np.float64)
            self.phi = np.ascontiguousarray(phi, np.float64)
            if self.phi.shape != (H * W, self.coef.shape[3]):
                raise ValueError(f"FastLUT: phi must be ({H * W}, {self.coef.shape[3]}), got {self.phi.shape}")
        self.dark = np.zeros((0, 0), np.float32) if dark is None else frame_planes_np(
            np.asarray(dark, np.float32)[None])

    def solve(self, frames, threads: int = 1):
        """Normals, mask and confidence of one RGB frame ``(H, W, 3)`` or ``(1, H, W, 3)`` (integer)."""
        H, W = self.shape
        M = H * W
        normals = np.empty((M, 3), np.float32)
        mask = np.empty(M, np.bool_)
        conf = np.empty(M, np.float32)
        meta = self.solve_into(frames, normals, mask, conf, threads)
        return self._result(normals, mask, conf, meta)

    def solve_into(self, frames, normals, mask, conf, threads: int = 1) -> dict:
        """:meth:`solve` into the caller's arrays (``normals (H * W, 3)`` float32, ``mask (H * W,)``
        bool, ``conf (H * W,)`` float32, C-contiguous: views of a chunk's arrays), nothing else
        allocated per frame; returns the result's meta (a recording's frames in parallel)."""
        f = self._check(frames)
        planes = frame_planes_np(f)
        dg, do, drift = self._drift_planes(f)
        M = self.shape[0] * self.shape[1]
        run_split(lambda a, b: _lut_kernel(planes, self.dark, self.ref, self.lo, self.width, self.bins, self.filled,
                                           self.support, self.table, self.coef, self.phi, self.apply_tilt, self.gain,
                                           self.limit, dg, do, a, b, normals, mask, conf), M, threads)
        return self._meta("lut", drift)


# Eigen's float tanh (generic_fast_tanh_float): a (13, 6) rational approximation on [-7.9, 7.9],
# within 4e-7 of tanh; SiLU(x) = x (1 + tanh(x / 2)) / 2 then needs no exp and vectorises in one
# loop with one division (3x faster than exp and a division in separate passes).
_TA = (-2.76076847742355e-16, 2.00018790482477e-13, -8.60467152213735e-11, 5.12229709037114e-08,
       1.48572235717979e-05, 6.37261928875436e-04, 4.89352455891786e-03)
_TB = (1.19825839466702e-06, 1.18534705686654e-04, 2.26843463243900e-03, 4.89352518554385e-03)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _silu(v):  # pragma: no cover - compiled
    x = min(max(np.float32(0.5) * v, np.float32(-7.90531110763549805)), np.float32(7.90531110763549805))
    x2 = x * x
    p = np.float32(_TA[0])
    p = p * x2 + np.float32(_TA[1])
    p = p * x2 + np.float32(_TA[2])
    p = p * x2 + np.float32(_TA[3])
    p = p * x2 + np.float32(_TA[4])
    p = p * x2 + np.float32(_TA[5])
    p = p * x2 + np.float32(_TA[6])
    q = np.float32(_TB[0])
    q = q * x2 + np.float32(_TB[1])
    q = q * x2 + np.float32(_TB[2])
    q = q * x2 + np.float32(_TB[3])
    return v * (np.float32(0.5) + np.float32(0.5) * (p * x / q))


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _mlp_kernel(obs, dark, ref, inv_scale, fixed, Wd, Wh, bh, Wo, bo, drift_g, drift_o, start, stop, out):  # pragma: no cover  # noqa: C901 - compiled
    """Pixels ``start:stop`` (a multiple of 512) through the network, a block at a time.

    ``fixed (nb, K, 512)``: the first layer without the colour change; ``Wd (K, N)``: its
    colour-change columns (the feature scaling folded in); ``Wh (L, K, K)``, ``bh (L, K)``:
    the hidden layers; ``Wo (2, K)``, ``bo (2,)``: the output layer; ``out (2, M)`` float32;
    ``drift_g``, ``drift_o (N,)``: the frame's drift per pattern-channel (inverse gain, offset;
    empty: none), as in :func:`_lut_kernel`.
    """
    N = obs.shape[0]
    K = Wd.shape[0]
    has_dark = dark.shape[0] > 0
    has_drift = drift_g.shape[0] > 0
    h = np.zeros((K, 512), np.float32)  # columns past a short last block stay finite
    h2 = np.zeros((K, 512), np.float32)
    o2 = np.empty((2, 512), np.float32)
    d = np.zeros((N, 512), np.float32)
    for j0 in range(start, stop, 512):
        j1 = min(stop, j0 + 512)
        B = j1 - j0
        blk = j0 // 512
        fb = fixed[blk]
        for k in range(N):
            o = obs[k, j0:j1]
            rk = ref[k, j0:j1]
            for j in range(B):
                v = np.float32(o[j])
                if has_dark:
                    v = v - dark[k, j0 + j]
                if has_drift:
                    v = np.float32((np.float64(v) - drift_o[k]) * drift_g[k])
                d[k, j] = (v - rk[j]) * inv_scale
        for i in range(K):
            # Whole 512 columns (a fixed trip count vectorises; a short block's extra columns
            # are finite and never written out). Blocks of 1024 to 4096 pixels (one longer
            # GEMM a layer) measured slower: 7.2 -> 9.7 ms a frame.
            hi = h[i]
            fi = fb[i]
            for j in range(512):
                hi[j] = fi[j]
            for k in range(N):
                w = Wd[i, k]
                dk = d[k]
                for j in range(512):
                    hi[j] += w * dk[j]
        for i in range(K):  # SiLU of the first layer
            hi = h[i]
            for j in range(512):
                hi[j] = _silu(hi[j])
        src = h
        dst = h2
        for layer in range(Wh.shape[0]):
            # The next layer: one small GEMM through BLAS (a hand-written loop did not vectorise
            # as well: 80-120 ns per pixel against 46), then bias and SiLU in one pass.
            np.dot(Wh[layer], src, dst)
            for o_ in range(K):
                di = dst[o_]
                b = bh[layer, o_]
                for j in range(512):
                    di[j] = _silu(di[j] + b)
            src, dst = dst, src
        np.dot(Wo, src, o2)
        for o_ in range(2):
            oo = out[o_]
            for j in range(B):
                oo[j0 + j] = o2[o_, j] + bo[o_]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _finite3(a, b, c):  # pragma: no cover - compiled
    """All three finite: ``x - x`` is 0 for a finite ``x`` and NaN otherwise (np.isfinite is a
    call LLVM does not vectorise)."""
    return (a - a == 0.0) & (b - b == 0.0) & (c - c == 0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _mlp_finish(outs, apply, gain, limit, start, stop, normals, mask, conf):  # pragma: no cover  # noqa: C901 - compiled
    """``MLPModel._predict_features`` on raw outputs ``(members, 2, M)``: the members' mean
    (float64), their spread ``s`` (confidence ``exp(-s / 0.05)``), outputs outside the unit disc
    shrunk onto ``|n_xy|^2 = 0.996``, ``n_z``; then :func:`_finish_one`. ``normals (3, M)``.

    Blocks of 512 pixels (loops of a fixed 512: with a computed trip count they did not
    vectorise), the member loops outside the pixel loops and the exponential in a loop of its
    own (no vector ``exp`` without SVML), so the rest vectorises.
    """
    m = outs.shape[0]
    g_ = gain if apply else 1.0
    lim_ = limit if apply else np.inf
    A = np.empty(512)
    Bv = np.empty(512)
    V = np.empty(512)
    tail = np.zeros((m, 2, 512), np.float32)
    out = np.empty((5, 512), np.float32)  # n_x, n_y, n_z, valid, confidence
    for j0 in range(start, stop, 512):
        B = min(stop, j0 + 512) - j0
        if B < 512:
            for k in range(m):
                for o in range(2):
                    for j in range(B):
                        tail[k, o, j] = outs[k, o, j0 + j]
        A[:] = 0.0
        Bv[:] = 0.0
        V[:] = 0.0
        for k in range(m):
            ka = outs[k, 0, j0:j0 + 512] if B == 512 else tail[k, 0]
            kb = outs[k, 1, j0:j0 + 512] if B == 512 else tail[k, 1]
            for j in range(512):
                A[j] += np.float64(ka[j])
                Bv[j] += np.float64(kb[j])
        for j in range(512):
            A[j] /= m
            Bv[j] /= m
        if m > 1:
            for k in range(m):
                ka = outs[k, 0, j0:j0 + 512] if B == 512 else tail[k, 0]
                kb = outs[k, 1, j0:j0 + 512] if B == 512 else tail[k, 1]
                for j in range(512):
                    V[j] += (np.float64(ka[j]) - A[j]) ** 2 / m + (np.float64(kb[j]) - Bv[j]) ** 2 / m
            for j in range(B):
                V[j] = np.exp(-np.sqrt(V[j]) / 0.05)
        else:
            V[:] = 1.0  # one member: no spread, exp(0)
        for j in range(512):
            # _finish_one written without branches (selects; '&' not 'and'): it vectorises.
            a = A[j]
            b = Bv[j]
            r2 = a * a + b * b
            f = np.sqrt(0.996 / max(r2, 1e-12))
            f = f if r2 > 0.996 else 1.0
            a *= f
            b *= f
            c = np.sqrt(1.0 - (a * a + b * b))
            ok = _finite3(a, b, c)
            # The tilt correction, or (apply False) the identity: gain 1, no clip.
            a *= g_
            b *= g_
            mag = np.sqrt(a * a + b * b)
            f = lim_ / max(mag, 1e-12)
            f = f if mag > lim_ else 1.0
            a *= f
            b *= f
            c2 = 1.0 - (a * a + b * b)
            c2 = c2 if c2 > 0.0 else 0.0
            c2 = c2 if c2 < 1.0 else 1.0
            c = np.sqrt(c2) if apply else c
            good = ok & _finite3(a, b, c)
            nrm = np.sqrt(a * a + b * b + c * c)
            good = good & (nrm > 0.5)
            sc = 1.0 / max(nrm, 1e-12)
            out[0, j] = a * sc if good else 0.0
            out[1, j] = b * sc if good else 0.0
            out[2, j] = c * sc if good else 1.0
            out[3, j] = 1.0 if good else 0.0
            v = V[j]
            v = v if v > 0.0 else 0.0
            v = v if v < 1.0 else 1.0
            out[4, j] = v if good else 0.0
        for c_ in range(3):
            nc = normals[c_]
            for j in range(B):
                nc[j0 + j] = out[c_, j]
        for j in range(B):
            mask[j0 + j] = out[3, j] > 0
            conf[j0 + j] = out[4, j]


class FastMLP(_Base):
    """A calibration's MLP (every ensemble member) as one fused, compiled pass per frame.

    Parameters
    ----------
    members : list of list of (weight, bias)
        Per member, its ``Linear`` layers in order (numpy; ``weight (out, in)``): the first
        takes ``[a * d, r, uv]`` (``features="change+reference"``, ``a = 4``),
        ``[a * d, uv]`` (``"change"``) or ``[d + r, uv]`` (``"colour"``) with ``d = (I - ref) /
        input_scale``, ``r = ref / input_scale`` (``P * C`` values each), the last gives
        ``(n_x, n_y)``. Activations SiLU.
    reference : ndarray, shape (P, H, W, C)
    uv : ndarray, shape (H * W, T)
        The position terms the model feeds (``poly_terms(..., position_degree)[:, 1:]``: ``u, v``
        at degree 1, T = 2), or None without position input.
    input_scale : float
    features : str
    tilt_gain, max_tilt, dark, drift : as :class:`FastLUT`.
    """

    def __init__(self, members, reference, uv, *, input_scale: float = 255.0, features: str = "change+reference",
                 tilt_gain: float = 1.0, max_tilt=None, dark=None, markers=None, drift=None):
        super().__init__(np.asarray(reference).shape[1:3], reference, tilt_gain, max_tilt, markers, drift,
                         None if dark is None else np.broadcast_to(np.asarray(dark, np.float32),
                                                                   np.asarray(reference).shape[1:]))
        H, W = self.shape
        M = H * W
        N = self.num_patterns * self.channels
        ref = np.asarray(reference, np.float32)
        self.ref = frame_planes_np(ref)  # (N, M) float32
        self.inv_scale = np.float32(1.0 / float(input_scale))
        r = (self.ref / np.float32(input_scale)).T.astype(np.float64)  # (M, N), the model's r
        pos = np.zeros((M, 0)) if uv is None else np.asarray(uv, np.float64).reshape(M, -1)
        self.members = []
        for layers in members:
            W1, b1 = (np.asarray(a, np.float64) for a in layers[0])
            if features == "change+reference":
                Wd, rest, rest_in = 4.0 * W1[:, :N], W1[:, N:], np.concatenate([r, pos], 1)
            elif features == "change":
                Wd, rest, rest_in = 4.0 * W1[:, :N], W1[:, N:], pos
            elif features == "colour":
                Wd, rest, rest_in = W1[:, :N], np.concatenate([W1[:, :N], W1[:, N:]], 1), np.concatenate([r, pos], 1)
            else:
                raise ValueError(f"FastMLP: unknown features {features!r}")
            if rest.shape[1] != rest_in.shape[1]:
                raise ValueError(f"FastMLP: the first layer takes {W1.shape[1]} inputs, the features give "
                                 f"{N + rest_in.shape[1]}")
            fixed = (rest_in @ rest.T + b1).T  # (K, M): what does not change between frames
            hidden = layers[1:-1]
            K = W1.shape[0]
            Wh = np.stack([np.asarray(w, np.float32) for w, _ in hidden]) if hidden else np.zeros((0, K, K), np.float32)
            bh = np.stack([np.asarray(b, np.float32) for _, b in hidden]) if hidden else np.zeros((0, K), np.float32)
            Wo, bo = (np.asarray(a, np.float32) for a in layers[-1])
            self.members.append((blocked(fixed), np.ascontiguousarray(Wd, np.float32), np.ascontiguousarray(Wh),
                                 np.ascontiguousarray(bh), np.ascontiguousarray(Wo), np.ascontiguousarray(bo)))
        self.dark = np.zeros((0, 0), np.float32) if dark is None else frame_planes_np(
            np.broadcast_to(np.asarray(dark, np.float32), (self.num_patterns, H, W, self.channels)).copy())

    def outputs(self, frames, threads: int = 1) -> np.ndarray:
        """Raw network outputs ``(members, H * W, 2)`` float32 of one frame set ``(P, H, W, C)``."""
        return self._outputs(frames, threads)[0]

    def _outputs(self, frames, threads: int = 1):
        f = self._check(frames)
        planes = frame_planes_np(f)
        dg, do, drift = self._drift_planes(f)
        M = self.shape[0] * self.shape[1]
        outs = np.empty((len(self.members), 2, M), np.float32)  # planes: contiguous stores
        for m, (fixed, Wd, Wh, bh, Wo, bo) in enumerate(self.members):
            o = outs[m]
            run_split(lambda a, b: _mlp_kernel(planes, self.dark, self.ref, self.inv_scale, fixed, Wd, Wh, bh, Wo, bo,
                                               dg, do, a, b, o), M, threads)
        return outs.transpose(0, 2, 1), drift

    def solve(self, frames, threads: int = 1):
        """Normals, mask and confidence of one frame set ``(P, H, W, C)`` (integer); as
        ``MLPModel._predict_features`` then the output correction."""
        M = self.shape[0] * self.shape[1]
        planes = np.empty((3, M), np.float32)
        mask = np.empty(M, np.bool_)
        conf = np.empty(M, np.float32)
        meta = self._solve_planes(frames, planes, mask, conf, threads)
        # (M, 3) view of the planes (FastDST reads them back without a split).
        return self._result(planes.T, mask, conf, meta)

    def _solve_planes(self, frames, planes, mask, conf, threads: int = 1) -> dict:
        raw, drift = self._outputs(frames, threads)
        outs = np.ascontiguousarray(raw.transpose(0, 2, 1))  # (members, 2, M): no copy
        M = self.shape[0] * self.shape[1]
        run_split(lambda a, b: _mlp_finish(outs, self.apply_tilt, self.gain, self.limit, a, b, planes, mask, conf),
                  M, threads)
        return self._meta("mlp", drift)

    def solve_into(self, frames, normals, mask, conf, threads: int = 1) -> dict:
        """:meth:`solve` into the caller's arrays (``normals (H * W, 3)`` float32, ``mask (H * W,)``,
        ``conf (H * W,)``: views of a chunk's arrays); returns the result's meta."""
        M = self.shape[0] * self.shape[1]
        planes = np.empty((3, M), np.float32)
        meta = self._solve_planes(frames, planes, mask, conf, threads)
        normals[...] = planes.T
        return meta
