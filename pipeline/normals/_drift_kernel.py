"""The constant drift models' trimmed fit as one compiled pass (``offset``, ``gain_offset``).

:meth:`pipeline.normals.drift.DriftEstimator._fit_samples` in numpy makes some forty small
array calls per frame (three trimmed least-squares rounds over every pattern-channel): about
1.3 ms at 1000 samples on a quiet core, which a recording pays on every frame. The same
arithmetic per pattern-channel in Numba (the 1x1 or 2x2 normal equations summed directly, the
medians by sorting as numpy's): 0.1 ms. Equal to the numpy rounds to float64 rounding
(``tests/pipeline/normals/test_drift.py``); the ``field`` model (polynomials in the image
position) stays with numpy.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["fit_constant"]


@njit(cache=True, nogil=True)
def fit_constant(x, y, gain_model, trim, pivot):  # pragma: no cover - compiled  # noqa: C901
    """Per row ``m`` of the sampled reference ``x (M, N)`` and frame ``y (M, N)`` (float64): the
    trimmed least-squares ``y ~ g x + o`` (``gain_model``; the gain pulled toward 1 by a ridge of
    ``pivot``) or ``y - x ~ o``; three rounds, keeping the samples within ``trim`` robust sigmas.
    Returns ``(gain (M,), offset (M,), residual (M, N), keep (M, N))``."""
    M, N = x.shape
    K = 2 if gain_model else 1
    gain = np.ones(M)
    offset = np.zeros(M)
    res = np.zeros((M, N))
    keep = np.ones((M, N), np.bool_)
    t = np.empty(N)
    for m in range(M):
        for n in range(N):
            t[n] = y[m, n] if gain_model else y[m, n] - x[m, n]
        floor = 1e-3 * np.median(np.abs(t)) + 1e-9
        for _ in range(3):
            s_xx = 0.0
            s_x = 0.0
            s_1 = 0.0
            b_x = 0.0
            b_1 = 0.0
            for n in range(N):
                if keep[m, n]:
                    s_xx += x[m, n] * x[m, n]
                    s_x += x[m, n]
                    s_1 += 1.0
                    b_x += x[m, n] * t[n]
                    b_1 += t[n]
            if gain_model:
                ridge = s_1 * (pivot * abs(s_x) / max(s_1, 1.0)) ** 2
                g00 = s_xx + ridge
                g01 = s_x
                g11 = s_1
                r0 = b_x + ridge
                r1 = b_1
                eps = 1e-9 * (g00 + g11) / 2.0
                g00 += eps
                g11 += eps
                det = g00 * g11 - g01 * g01
                a = (r0 * g11 - g01 * r1) / det
                o = (g00 * r1 - g01 * r0) / det
            else:
                a = 1.0
                o = b_1 / (s_1 + 1e-9 * s_1)
            for n in range(N):
                res[m, n] = t[n] - (a * x[m, n] + o if gain_model else o)
            med = np.median(res[m])
            dev = np.abs(res[m] - med)
            sig = 1.4826 * np.median(dev)
            lim = trim * max(sig, floor)
            count = 0
            for n in range(N):
                keep[m, n] = dev[n] <= lim
                count += keep[m, n]
            if count < 2 * K + 2:
                for n in range(N):
                    keep[m, n] = True
            gain[m] = a
            offset[m] = o
    return gain, offset, res, keep
