"""Frankot–Chellappa (1988): project the gradient field onto integrable fields by FFT."""

from __future__ import annotations

import numpy as np
import scipy.fft

from pipeline.depth._common import DepthResult, anchor_to_border, pixel_gradients

__all__ = ["frankot_chellappa"]


def frankot_chellappa(normals, mm_per_px: float, mask=None, *, max_slope: float = 20.0,
                      workers: int | None = None) -> DepthResult:
    """Height map by Frankot–Chellappa.

    The FFT assumes a periodic field. A plane is not periodic, so the mean gradient is
    removed first and added back as a ramp: planes come out exact, and everything else is the
    classical least-squares projection with continuous frequencies.

    Parameters
    ----------
    normals : ndarray, shape (H, W, 3)
        Reconstruction-frame unit normals.
    mm_per_px : float
        Pixel pitch (mm).
    mask : ndarray, shape (H, W), bool, optional
        Invalid pixels are treated as flat (zero gradient).
    max_slope : float
        Slope clip (mm/mm).
    workers : int, optional
        FFT threads (scipy.fft).

    Returns
    -------
    DepthResult
        Heights in mm, anchored so the median over the image border is 0.

    Examples
    --------
    >>> from pipeline.base.frames import normals_from_height
    >>> yy, xx = np.mgrid[0:32, 0:32]
    >>> h = 0.2 * np.exp(-((xx - 15.5) ** 2 + (yy - 15.5) ** 2) / 20.0)
    >>> out = frankot_chellappa(normals_from_height(h, 0.1), 0.1)
    >>> bool(np.abs(out.height - h).max() < 0.01)
    True
    """
    gc, gr, m = pixel_gradients(normals, mask, mm_per_px, max_slope, "frankot_chellappa")
    H, W = gc.shape
    mc, mr = gc.mean(), gr.mean()
    Gc = scipy.fft.rfft2(gc - mc, workers=workers)
    Gr = scipy.fft.rfft2(gr - mr, workers=workers)
    u = (2.0 * np.pi * scipy.fft.rfftfreq(W)[None, :]).astype(gc.dtype)
    v = (2.0 * np.pi * scipy.fft.fftfreq(H)[:, None]).astype(gc.dtype)
    denom = u * u + v * v
    denom[0, 0] = 1.0
    Z = (-1j * u * Gc - 1j * v * Gr) / denom
    Z[0, 0] = 0.0
    h = scipy.fft.irfft2(Z, s=(H, W), workers=workers)
    h = h + mc * np.arange(W, dtype=h.dtype)[None, :] + mr * np.arange(H, dtype=h.dtype)[:, None]
    h = anchor_to_border(h, m)
    return DepthResult(height=h.astype(np.float32), mask=m,
                       meta={"integrator": "fc", "mm_per_px": float(mm_per_px), "max_slope": float(max_slope)})
