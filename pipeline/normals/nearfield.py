"""Near-field least squares: a different light matrix at every pixel.

``I_k(x) = rho(x) n(x) . L_k(x)`` with ``L_k(x)`` from the illumination stage
(:func:`sim.illumination_model.light_matrices`) or a near-field calibration. The light field
does not change between frames, so the per-pixel pseudo-inverse ``(A^-1 L^T)(x)`` is built
once (normal equations, or QR for the reference path) and a frame costs one weighted sum.
"""

from __future__ import annotations

import numpy as np  # noqa: F401 - the examples (doctests) use it
import torch

from pipeline.normals import _inputs, _lstsq, _xp
from pipeline.normals._linalg3 import inverse3
from pipeline.normals._lstsq import finalize
from pipeline.normals.masking import PixelMask
from pipeline.normals.result import NormalResult

__all__ = ["NearFieldSolver", "solve_nearfield"]

_METHODS = ("normal", "qr")


class NearFieldSolver:
    """Per-pixel photometric stereo with per-pixel light vectors.

    Parameters
    ----------
    lights : ndarray, shape (N_obs, H, W, 3)
        Light vector of each observation at each pixel (reconstruction frame), e.g.
        ``light_matrices(...)`` of shape ``(P, C, H, W, 3)`` reshaped to ``(P*C, H, W, 3)``.
    groups : ndarray, shape (N_obs,), optional
        Albedo group (camera channel) of each observation, as in :class:`FarFieldSolver`.
    method : {"normal", "qr"}
        ``"normal"``: batched 3x3 normal equations with a precomputed pseudo-inverse (fast).
        ``"qr"``: batched Householder QR of each pixel's ``(N_obs, 3)`` matrix (slower, better
        conditioned arithmetic; the reference the fast path is tested against).
    max_condition, albedo_iterations, device, dtype
        As in :class:`FarFieldSolver`.
    mask : ndarray, shape (H, W), optional
        Solve only these pixels: the light field is gathered on them once, here, and each
        :meth:`solve` gathers the observations' (:mod:`pipeline.normals.masking`); the other
        pixels come back invalid.

    Examples
    --------
    Two pixels with different light matrices, both solved exactly:

    >>> rng = np.random.default_rng(0)
    >>> L = rng.normal(size=(5, 1, 2, 3)); L[..., 2] = np.abs(L[..., 2]) + 1
    >>> n = np.array([0.0, 0.6, 0.8])
    >>> I = np.einsum("nhwk,k->nhw", L, n)
    >>> res = NearFieldSolver(L, dtype="float64").solve(I)
    >>> np.round(res.normals, 6).tolist()
    [[[0.0, 0.6, 0.8], [0.0, 0.6, 0.8]]]
    """

    def __init__(self, lights, *, groups=None, method: str = "normal", max_condition: float = 1e3,
                 albedo_iterations: int | None = None, device="cpu", dtype="float32", mask=None):
        if lights is None or len(getattr(lights, "shape", ())) != 4 or lights.shape[-1] != 3:
            raise ValueError(f"NearFieldSolver: lights must have shape (N_obs, H, W, 3), got "
                             f"{getattr(lights, 'shape', None)}")
        if method not in _METHODS:
            raise ValueError(f"NearFieldSolver: method must be one of {_METHODS}, got {method!r}")
        self.full_shape = (int(lights.shape[1]), int(lights.shape[2]))
        self.pixels = None if mask is None else PixelMask(mask, self.full_shape, "NearFieldSolver")
        if self.pixels is not None:
            lights = self.pixels.gather(lights, axis=1)
        self.device = torch.device(device)
        self.dtype = _xp.float_dtype(dtype, self.device)
        self.n_obs, self.H, self.W = (int(s) for s in lights.shape[:3])
        self.method = method
        self.groups, self.num_groups = _inputs.check_groups(groups, self.n_obs, "NearFieldSolver", self.device)
        self.selectors = _lstsq.group_selectors(self.groups, self.num_groups, self.n_obs)
        self.max_condition = float(max_condition)
        self.L, ok = _inputs.flatten_lights(lights, self.dtype, self.device)  # (N, 3, M)
        self.iterations = _lstsq.albedo_iterations(albedo_iterations, self.L, self.selectors, self.groups,
                                             self.num_groups)
        self.w0 = None if bool(ok.all()) else ok.to(self.dtype)
        # The light field is fixed: per-pixel moments, inverse and condition once per model.
        self.Q = torch.stack([_lstsq.gram_pixel(self.L[sel], None if self.w0 is None else self.w0[sel])
                              for sel in self.selectors])
        self.inv, _ = inverse3(self.Q.sum(0))
        self.cond = _lstsq.condition(self.L, self.w0)

    def solve(self, observations) -> NormalResult:
        """Normals of one observation stack ``(N_obs, H, W)``; NaN/Inf observations are ignored."""
        N, H, W = _inputs.check_observations(observations, "NearFieldSolver.solve")
        if (N, H, W) != (self.n_obs,) + self.full_shape:
            raise ValueError(f"NearFieldSolver.solve: expected observations of shape "
                             f"({self.n_obs}, {self.full_shape[0]}, {self.full_shape[1]}), got "
                             f"{tuple(observations.shape)}")
        if self.pixels is not None:
            return self.pixels.scatter(self._solve(self.pixels.gather(observations, axis=1)))
        return self._solve(observations)

    def _solve(self, observations) -> NormalResult:
        N, H, W = tuple(observations.shape)
        I, finite = _inputs.flatten_observations(observations, self.dtype, self.device)
        if finite is None:
            w = self.w0
            m = _lstsq.moments(I, self.L, w, self.selectors, Q=self.Q)
            inv, cond = self.inv, self.cond
        else:
            w = finite.to(self.dtype) if self.w0 is None else finite.to(self.dtype) * self.w0
            m = _lstsq.moments(I, self.L, w, self.selectors)
            inv, _ = inverse3(m.Q.sum(0))
            cond = _lstsq.condition(self.L, w)
        if self.method == "qr":
            b = _qr_solve(I, self.L, torch.ones_like(I) if w is None else w)
        else:
            b = _lstsq.solve(m, inv, self.iterations)
        return finalize(b, m, cond, (H, W), max_condition=self.max_condition, finite_inputs=finite is None,
                        meta={"solver": "nearfield", "method": self.method, "max_condition": self.max_condition})


def _qr_solve(I: torch.Tensor, L: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Per-pixel weighted least squares by QR of ``(M, N, 3)`` systems; rank-deficient -> 0.

    One albedo (no per-group alternation): the reference path for the normal equations.
    """
    sw = torch.sqrt(w).T  # (M, N)
    A = L.permute(2, 0, 1) * sw[..., None]  # (M, N, 3)
    y = (I.T * sw)[..., None]  # (M, N, 1)
    if A.shape[1] < 3:
        return torch.zeros((3, A.shape[0]), dtype=I.dtype, device=I.device)
    Q, R = torch.linalg.qr(A, mode="reduced")
    d = torch.diagonal(R, dim1=-2, dim2=-1).abs()
    tol = d.amax(-1, keepdim=True) * (torch.finfo(I.dtype).eps * 1e3)
    ok = (d > tol).all(-1) & (d.amax(-1) > 0)
    eye = torch.eye(3, dtype=I.dtype, device=I.device).expand_as(R)
    R = torch.where(ok[:, None, None], R, eye)
    b = torch.linalg.solve_triangular(R, Q.transpose(1, 2) @ y, upper=True)[..., 0]
    b = torch.where(ok[:, None] & torch.isfinite(b).all(-1, keepdim=True), b, torch.zeros_like(b))
    return b.T.contiguous()


def solve_nearfield(observations, lights, mask=None, **kwargs) -> NormalResult:
    """One-shot :class:`NearFieldSolver` (``observations (N_obs, H, W)``, ``lights (N_obs, H, W, 3)``,
    optional ``mask (H, W)`` of the pixels to solve)."""
    return NearFieldSolver(lights, mask=mask, **kwargs).solve(observations)
