"""Depth integration: normals -> height map in mm (positive toward the camera, sim.frames).

- :func:`frankot_chellappa` (``fc``): FFT projection (periodic; mean slope kept as a ramp);
- :func:`poisson_dct` (``dct``): Poisson, Neumann border;
- :func:`poisson_dst` (``dst``): Poisson, zero height on the border pixels;
- :func:`sparse_lstsq` (``sparse``): least squares on the valid pixels only, PCG.

:func:`integrate` dispatches by name.
"""

from __future__ import annotations

from pipeline.depth._common import DepthResult
from pipeline.depth.fourier import frankot_chellappa
from pipeline.depth.poisson import poisson_dct, poisson_dst
from pipeline.depth.sparse import sparse_lstsq

__all__ = ["DepthResult", "frankot_chellappa", "poisson_dct", "poisson_dst", "sparse_lstsq", "integrate",
           "INTEGRATORS"]

#: Integrator names accepted by the CLI, mapped to their functions.
INTEGRATORS = {"fc": frankot_chellappa, "dct": poisson_dct, "dst": poisson_dst, "sparse": sparse_lstsq}


def integrate(normals, mm_per_px: float, mask=None, method: str = "dst", **kwargs) -> DepthResult:
    """Integrate normals ``(H, W, 3)`` to heights with the integrator named ``method``.

    Examples
    --------
    >>> import numpy as np
    >>> flat = np.zeros((3, 4, 3)); flat[..., 2] = 1.0
    >>> float(np.abs(integrate(flat, 0.1, method="fc").height).max())
    0.0
    """
    try:
        func = INTEGRATORS[method]
    except KeyError:
        raise ValueError(f"integrate: method must be one of {sorted(INTEGRATORS)}, got {method!r}") from None
    return func(normals, mm_per_px, mask, **kwargs)
