"""Depth integration: normals -> height map in mm (positive toward the camera, pipeline.base.frames).

- :func:`frankot_chellappa` (``fc``): FFT projection (periodic; mean slope kept as a ramp);
- :func:`poisson_dct` (``dct``): Poisson, Neumann border;
- :func:`poisson_dst` (``dst``): Poisson, zero height on the border pixels;
- :func:`sparse_lstsq` (``sparse``): least squares on the valid pixels only, PCG.

:func:`integrate` dispatches by name through the integrator registry
(:data:`pipeline.base.registry.INTEGRATORS`), where a new integrator is registered.
"""

from __future__ import annotations

from pipeline.base.registry import INTEGRATORS
from pipeline.depth._common import DepthResult
from pipeline.depth.fourier import frankot_chellappa
from pipeline.depth.poisson import poisson_dct, poisson_dst
from pipeline.depth.sparse import sparse_lstsq

__all__ = ["DepthResult", "frankot_chellappa", "poisson_dct", "poisson_dst", "sparse_lstsq", "integrate"]


def integrate(normals, mm_per_px: float, mask=None, method: str = "dst", **kwargs) -> DepthResult:
    """Integrate normals ``(H, W, 3)`` to heights with the integrator named ``method``.

    Examples
    --------
    >>> import numpy as np
    >>> flat = np.zeros((3, 4, 3)); flat[..., 2] = 1.0
    >>> float(np.abs(integrate(flat, 0.1, method="fc").height).max())
    0.0
    """
    if method not in INTEGRATORS:
        raise ValueError(f"integrate: method must be one of {list(INTEGRATORS.names())}, got {method!r}")
    return INTEGRATORS.load(method)(normals, mm_per_px, mask, **kwargs)
