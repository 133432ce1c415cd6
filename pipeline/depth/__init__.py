"""Depth integration: normals -> height map in mm (positive toward the camera, pipeline.base.frames).

- :func:`frankot_chellappa` (``fc``): FFT projection (periodic; mean slope kept as a ramp);
- :func:`poisson_dct` (``dct``): Poisson, Neumann border;
- :func:`poisson_dst` (``dst``): Poisson, zero height on the border pixels;
- :func:`sparse_lstsq` (``sparse``): least squares on the valid pixels only, PCG.

:func:`integrate` dispatches by name through the integrator registry
(:data:`pipeline.base.registry.INTEGRATORS`), where a new integrator is registered;
:func:`frame_integrator` gives live use an integrator's registered fast path (``dst``:
:class:`pipeline.depth.fast.FastDST`), else the eager one, frame after frame.
"""

from __future__ import annotations

from pipeline.base.lazy import lazy_names
from pipeline.base.registry import INTEGRATORS
from pipeline.depth._common import DepthResult

# The integrators are imported on first use (PEP 562): ``sparse`` loads scipy.sparse and
# scipy.optimize, half a second a live start (``pipeline.depth.fast``) does not need.
_WHERE = {"frankot_chellappa": "fourier", "poisson_dct": "poisson", "poisson_dst": "poisson",
          "sparse_lstsq": "sparse"}

__getattr__, __dir__ = lazy_names(__name__, _WHERE, globals())

__all__ = ["DepthResult", "frankot_chellappa", "poisson_dct", "poisson_dst", "sparse_lstsq", "integrate",
           "frame_integrator", "FrameIntegrator"]


def integrate(normals, mm_per_px: float, mask=None, method: str = "dst", *, region=None, margin: int = 2,
              **kwargs) -> DepthResult:
    """Integrate normals ``(H, W, 3)`` to heights with the integrator named ``method``.

    Parameters
    ----------
    normals : ndarray, shape (H, W, 3)
    mm_per_px : float
    mask : ndarray, shape (H, W), bool, optional
        Valid normals (invalid pixels are flat for the rectangle solvers, left out by ``sparse``).
    method : {"fc", "dct", "dst", "sparse"}
    region : ndarray, shape (H, W), bool, optional
        The object (the capture's or the user's mask): ``sparse`` solves on ``mask & region``;
        the rectangular integrators (``fc``, ``dct``, ``dst``) solve the region's bounding box
        grown by ``margin`` pixels (its border then lies on flat, invalid pixels) instead of the
        whole frame. Outside the region heights are 0 and the mask False.

    Examples
    --------
    >>> import numpy as np
    >>> flat = np.zeros((3, 4, 3)); flat[..., 2] = 1.0
    >>> float(np.abs(integrate(flat, 0.1, method="fc").height).max())
    0.0
    >>> r = np.zeros((3, 4), bool); r[1, 1:3] = True
    >>> integrate(flat, 0.1, method="dst", region=r).mask.astype(int).tolist()
    [[0, 0, 0, 0], [0, 1, 1, 0], [0, 0, 0, 0]]
    """
    if method not in INTEGRATORS:
        raise ValueError(f"integrate: method must be one of {list(INTEGRATORS.names())}, got {method!r}")
    func = INTEGRATORS.load(method)
    if region is None:
        return func(normals, mm_per_px, mask, **kwargs)
    import numpy as np

    from pipeline.base.pixel_mask import PixelMask
    from pipeline.depth._common import check_mask

    n = np.asarray(normals)
    shape = n.shape[:2]
    pm = PixelMask(region, shape, "integrate: region")
    valid = check_mask(mask, shape, "integrate") & pm.mask
    if method == "sparse":
        out = func(n, mm_per_px, valid, **kwargs)
        return DepthResult(np.where(pm.mask, out.height, 0).astype(np.float32), out.mask & pm.mask, out.meta)
    rows, cols = pm.bbox(margin)
    out = func(n[rows, cols], mm_per_px, valid[rows, cols], **kwargs)
    height = np.zeros(shape, np.float32)
    height[rows, cols] = out.height
    m = np.zeros(shape, bool)
    m[rows, cols] = out.mask
    meta = dict(out.meta, bbox=[rows.start, rows.stop, cols.start, cols.stop])
    return DepthResult(np.where(pm.mask, height, 0).astype(np.float32), m & pm.mask, meta)


class FrameIntegrator:
    """An integrator by name on one frame's normals at a time (the eager path of
    :func:`frame_integrator`).

    Examples
    --------
    >>> import numpy as np
    >>> flat = np.zeros((3, 4, 3), np.float32); flat[..., 2] = 1.0
    >>> fi = FrameIntegrator("fc", (3, 4), 0.1)
    >>> fi.method, float(np.abs(fi.integrate(flat).height).max())
    ('eager', 0.0)
    """

    def __init__(self, name: str, shape, mm_per_px: float):
        self.name = INTEGRATORS.check(name)
        self.shape = (int(shape[0]), int(shape[1]))
        self.mm_per_px = float(mm_per_px)
        self.method = "eager"

    def integrate(self, normals, mask=None) -> DepthResult:
        """Heights of normals ``(H, W, 3)`` (``mask``: the valid ones)."""
        return integrate(normals, self.mm_per_px, mask, method=self.name)


def frame_integrator(name: str, shape, mm_per_px: float, *, workers: int = 1, fast: bool = True):
    """The per-frame integrator of ``name`` for normals of ``shape`` (H, W): its registered fast
    path (``info["fast"]`` in :data:`pipeline.base.registry.INTEGRATORS`), else
    :class:`FrameIntegrator`. Either has ``integrate(normals, mask) -> DepthResult`` and
    ``method`` (``fast``/``eager``).

    Examples
    --------
    >>> frame_integrator("dst", (8, 8), 0.1).method, frame_integrator("sparse", (8, 8), 0.1).method
    ('fast', 'eager')
    """
    build = INTEGRATORS.fast(name) if fast else None
    if build is None:
        return FrameIntegrator(name, shape, mm_per_px)
    return build(shape, mm_per_px, workers=workers)
