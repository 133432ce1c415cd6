"""Far-field least squares (Woodham 1980): one light vector per observation for all pixels.

``I_k(x) = rho(x) n(x) . L_k``. The light matrix is the same everywhere, so its
pseudo-inverse is computed once and a frame costs one ``(3, N) @ (N, H*W)`` matmul.

On the CPU the solve runs on numpy arrays and this module does not import torch (a one-shot
``reconstruct --solver lstsq`` would spend most of its start importing it); a device or
``compile`` runs the same code (:mod:`pipeline.normals._lstsq`) on torch tensors
(:func:`pipeline.normals._xp.solve_device`).
"""

from __future__ import annotations

import numpy as np

from pipeline.normals import _inputs, _lstsq, _xp
from pipeline.normals._linalg3 import condition_from_gram, inverse3
from pipeline.normals._lstsq import concat, finalize, finalize_tensors, to_result
from pipeline.normals.masking import PixelMask, masked_solve
from pipeline.normals.result import NormalResult

__all__ = ["FarFieldSolver", "solve_farfield"]


class FarFieldSolver:
    """Woodham photometric stereo with a precomputed pseudo-inverse.

    Parameters
    ----------
    lights : ndarray, shape (N_obs, 3)
        Light vector of each observation (reconstruction frame, intensity folded in), e.g.
        a far-field calibration's ``(P, C, 3)`` reshaped to ``(P*C, 3)``.
    groups : ndarray, shape (N_obs,), optional
        Albedo group of each observation (the camera channel): albedo is then estimated per
        group (given the normal).
    max_condition : float
        Pixels whose light matrix is worse conditioned are masked.
    albedo_iterations : int
        Alternation steps that refine the normal for per-group albedo (needs at least three
        observations per group; see :func:`pipeline.normals._lstsq.solve`). Useful only when
        the camera channels see different light directions (coloured patterns) and the
        albedo is coloured. None (default): 3 when the channels' lights differ (not one
        scalar multiple of each other), else 0 (the joint solve is exact then).
    device, dtype
        Device and float dtype of the computation: ``"cpu"`` computes with numpy (torch is
        not imported), any other device (``"cuda"``) with torch tensors there.
    compile : bool
        Solve through :mod:`pipeline.normals.fused`, one ``torch.compile``-d loop over pixels
        (about 4x faster per frame; the first frame of each image size pays a few seconds
        of compilation, so it is for live streams and long recordings). Used when the
        observations are finite, every light is finite and no albedo alternation is asked
        for; otherwise, or when compilation fails (a warning says why), the eager solver
        runs. Results agree with the eager solver to float rounding. Computes with torch
        (on ``device``).

    Examples
    --------
    A plane tilted toward +x under four lights, solved exactly:

    >>> L = np.array([[0, 0, 1.0], [0.5, 0, 1], [0, 0.5, 1], [-0.5, -0.5, 1]])
    >>> n = np.array([0.6, 0.0, 0.8])
    >>> I = np.broadcast_to((L @ n * 2.0)[:, None, None], (4, 2, 3))
    >>> res = FarFieldSolver(L, dtype="float64").solve(I)
    >>> (np.round(res.normals[0, 0], 6) + 0.0).tolist(), round(float(res.albedo[0, 0, 0]), 6), bool(res.mask.all())
    ([0.6, 0.0, 0.8], 2.0, True)
    """

    def __init__(self, lights, *, groups=None, max_condition: float = 1e3, albedo_iterations: int | None = None,
                 device="cpu", dtype="float32", compile: bool = False):
        L = np.asarray(lights, dtype=np.float64)
        if L.ndim != 2 or L.shape[1] != 3 or L.shape[0] < 1:
            raise ValueError(f"FarFieldSolver: lights must have shape (N_obs, 3), got {L.shape}")
        self.device = _xp.solve_device(device, compile)  # None: numpy on the CPU
        self.dtype = _xp.float_dtype(dtype, self.device)
        self.n_obs = L.shape[0]
        self.groups, self.num_groups = _inputs.check_groups(groups, self.n_obs, "FarFieldSolver", self.device)
        self.selectors = _lstsq.group_selectors(self.groups, self.num_groups, self.n_obs)
        self.max_condition = float(max_condition)
        self.L, row_ok = _inputs.flatten_lights(L, self.dtype, self.device)
        self.iterations = _lstsq.albedo_iterations(albedo_iterations, self.L, self.selectors, self.groups,
                                             self.num_groups)
        # Rows without a finite light are dropped by weight; all rows good -> unit weights.
        self.w_rows = None if bool(row_ok.all()) else _xp.astype(row_ok, self.dtype)[:, None]
        with np.errstate(all="ignore"):  # huge lights overflow float32: their pixels are masked
            self.Q, self.inv, self.cond = self._shared_moments(L)
        self.compile = bool(compile) and self.w_rows is None and self.iterations == 0
        self.group_tuple = tuple(self.groups.tolist()) if self.groups is not None else (0,) * self.n_obs

    def _shared_moments(self, L: np.ndarray) -> tuple:
        """The light matrix is the same at every pixel: its moments ``Q (G, 3, 3, 1)``, inverse
        ``(3, 3, 1)`` and condition ``(1,)`` are computed once, in float64, and a frame costs one
        ``(3, N) @ (N, M)`` product per group."""
        L64 = _xp.asarray(np.where(np.isfinite(L), L, 0.0), "float64", self.device)
        Q64 = _xp.namespace(L64).stack([_lstsq.gram_shared(L64[sel], None) for sel in self.selectors])
        inv64, _ = inverse3(Q64.sum(0))
        cond = condition_from_gram(Q64.sum(0))
        return _xp.astype(Q64, self.dtype), _xp.astype(inv64, self.dtype), _xp.astype(cond, self.dtype)

    def solve(self, observations, mask=None) -> NormalResult:
        """Normals of one observation stack ``(N_obs, H, W)`` (numpy or torch, any real dtype).

        NaN/Inf observations are ignored per pixel (a slower per-pixel solve is used then).
        ``mask (H, W)``: solve only those pixels (:mod:`pipeline.normals.masking`); the others
        come back invalid.
        """
        if mask is not None:
            return masked_solve(lambda obs, _: self.solve(obs), observations, mask, name="FarFieldSolver.solve")
        N, H, W = _inputs.check_observations(observations, "FarFieldSolver.solve")
        if N != self.n_obs:
            raise ValueError(f"FarFieldSolver.solve: expected {self.n_obs} observations, got shape "
                             f"{tuple(observations.shape)}")
        with np.errstate(all="ignore"):  # overflow and 0/0 are masked below, as torch does silently
            return self._solve(observations, N, H, W)

    def _solve(self, observations, N: int, H: int, W: int) -> NormalResult:
        if self.compile:
            integer = _inputs.is_integer(observations)
            X = (_xp.integers(observations, self.device) if integer
                 else _xp.asarray(observations, self.dtype, self.device)).reshape(N, H * W)
            if integer or _all_moderate(X):
                out = self._solve_fused(list(X.unbind(0)), H, W)
                if out is not None:
                    return out
        if self.w_rows is None and _inputs.is_integer(observations):
            X = _xp.integers(observations, self.device).reshape(N, H * W)
            return self._solve_chunks(lambda a, b: X[:, a:b], H, W)
        I, finite = _inputs.flatten_observations(observations, self.dtype, self.device)
        fast = finite is None and self.w_rows is None
        if fast:
            m = _lstsq.moments(I, self.L, None, self.selectors, Q=self.Q)
            inv, cond = self.inv, self.cond
        else:
            w = _xp.namespace(I).ones_like(I) if finite is None else _xp.astype(finite, self.dtype)
            if self.w_rows is not None:
                w = w * self.w_rows
            m = _lstsq.moments(I, self.L, w, self.selectors)
            inv, _ = inverse3(m.Q.sum(0))
            cond = _lstsq.condition(self.L, w)
        b = _lstsq.solve(m, inv, self.iterations)
        # Finite floats can still overflow in the squares (1e30 ** 2 in float32): only integer
        # observations may skip the scrubbing.
        return finalize(b, m, cond, (H, W), max_condition=self.max_condition,
                        finite_inputs=fast and _inputs.is_integer(observations),
                        meta=_meta(self))

    def solve_frames(self, frames, mask=None) -> NormalResult:
        """Normals of one capture's frames ``(P, H, W, C)`` (observations pattern-major,
        channel-minor, as ``P * C == N_obs``); integer frames skip the transposing copy.
        ``mask (H, W)``: gather those pixels from the frames once, solve only them."""
        shape = tuple(frames.shape)
        if len(shape) != 4 or shape[0] * shape[3] != self.n_obs:
            raise ValueError(f"FarFieldSolver.solve_frames: expected frames (P, H, W, C) with P*C = {self.n_obs}, "
                             f"got {shape}")
        P, H, W, C = shape
        if mask is not None:
            pm = PixelMask(mask, (H, W), "FarFieldSolver.solve_frames")
            return pm.scatter(self.solve(pm.gather_frames(frames)))
        if self.compile and (_inputs.is_integer(frames) or _all_moderate(frames)):
            from pipeline.normals import fused

            planes = fused.frame_planes(frames if not _xp.is_tensor(frames) else frames.to(self.device))
            out = self._solve_fused([p.to(self.device) for p in planes], H, W)
            if out is not None:
                return out
        if self.w_rows is None and _inputs.is_integer(frames):
            X = _xp.integers(frames, self.device).reshape(P, H * W, C)
            with np.errstate(all="ignore"):
                return self._solve_chunks(lambda a, b: X[:, a:b].swapaxes(1, 2).reshape(self.n_obs, -1), H, W)
        return self.solve(_xp.to_numpy(frames).transpose(0, 3, 1, 2).reshape(P * C, H, W))

    def _solve_fused(self, planes: list, H: int, W: int) -> NormalResult | None:
        """The compiled path on finite observation planes; None when compilation failed."""
        from pipeline.normals import fused

        groups = self.group_tuple
        usable = self.n_obs >= 3 and float(self.cond) <= self.max_condition
        try:
            n, rho, res, ok = fused.compiled_farfield()(planes, self.L, self.inv.reshape(3, 3),
                                                         self.Q.reshape(-1, 3, 3), groups, usable)
        except Exception as err:  # no C++ compiler, unsupported device...: the eager path is exact too
            fused.compile_failed(err)
            self.compile = False
            return None
        out_dtype = _xp.numpy_dtype(self.dtype).type
        return NormalResult(normals=n.cpu().numpy().reshape(H, W, 3), albedo=rho.cpu().numpy().reshape(H, W, -1),
                            residual=res.cpu().numpy().reshape(H, W), mask=ok.cpu().numpy().reshape(H, W),
                            condition=np.full((H, W), float(self.cond), dtype=out_dtype),
                            count=np.full((H, W), self.n_obs, dtype=np.int32), meta=_meta(self))

    def _solve_chunks(self, get, H: int, W: int) -> NormalResult:
        """Integer observations, all lights finite: solve chunk by chunk of pixels."""
        parts = []
        for a, b in _inputs.chunks(H * W, self.device):
            I = _xp.astype(get(a, b), self.dtype)
            m = _lstsq.moments(I, self.L, None, self.selectors, Q=self.Q)
            bb = _lstsq.solve(m, self.inv, self.iterations)
            parts.append(finalize_tensors(bb, m, self.cond, max_condition=self.max_condition, finite_inputs=True))
        return to_result(concat(parts), (H, W), _meta(self))


#: Float observations up to this magnitude cannot overflow the kernel's sums of squares in float32.
_MODERATE = 1e15


def _all_moderate(x) -> bool:
    """Finite and small enough for the fused kernel (it has no overflow scrubbing)."""
    a = x.abs().max() if _xp.is_tensor(x) else np.abs(np.asarray(x)).max()
    return bool(a < _MODERATE)  # False for NaN and Inf too


def _meta(self) -> dict:
    return {"solver": "lstsq", "model": "far-field", "max_condition": self.max_condition}


def solve_farfield(observations, lights, mask=None, **kwargs) -> NormalResult:
    """One-shot :class:`FarFieldSolver` (``observations (N_obs, H, W)``, ``lights (N_obs, 3)``,
    optional ``mask (H, W)`` of the pixels to solve).

    Examples
    --------
    >>> L = np.eye(3)
    >>> res = solve_farfield(np.zeros((3, 1, 1)), L)   # a black pixel has no normal
    >>> res.mask.tolist(), res.normals[0, 0].tolist()
    ([[False]], [0.0, 0.0, 1.0])
    """
    return FarFieldSolver(lights, **kwargs).solve(observations, mask=mask)
