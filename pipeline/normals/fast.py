"""The live near-field path: normal-equation factors precomputed once, a frame is one fused pass.

Why: the per-pixel light matrices ``L(x) (N, 3)`` of a calibration (or an illumination model)
never change between frames, so everything that depends only on them (the per-group Gram
matrices ``Q_g(x) = sum_{k in g} L_k L_k^T``, the inverse of ``sum_g Q_g``, the condition
number and the validity it implies) is computed once, in float64, by :class:`NearFieldFast`.
A frame then costs one pass that reads each observation once: per pixel the moments
``r_g = sum_k I_k L_k`` and ``S_g = sum_k I_k^2`` (3N + N multiply-adds), ``b = A^-1 sum_g r_g``,
the per-group albedo ``rho_g = n.r_g / n^T Q_g n`` and the residual from the same moments.
This is exactly the eager :class:`pipeline.normals.nearfield.NearFieldSolver` (the same
normal equations, the same per-group albedo alternation when the channels see different
lights, the same masks), which stays as the reference: ``tests/pipeline/normals/test_fast_paths.py``
pins the two together to float32 rounding.

The kernels (:mod:`pipeline.normals._fast_kernels`) are Numba, compiled once and cached on disk
(``cache=True``; ``NUMBA_CACHE_DIR`` moves the cache): a first use in a fresh process loads
them in well under a second. They work on blocks of 512 pixels with pixel-contiguous planes
(each block's observations de-interleaved from the camera's frames in the kernel, the light
field stored in blocks), so the inner loops run over pixels and vectorise. One frame
(:meth:`NearFieldFast.solve`, live) and a stack of frames (:meth:`NearFieldFast.solve_batch`,
throughput: :mod:`pipeline.frame_pipeline.cpu_batch`) go through the same kernel.

Integer frames only (uint8/uint16: no NaN can reach the moments); float frames with NaN/Inf
go to the eager solver. Lights that are not finite at a pixel make that pixel invalid here
(the eager solver would down-weight the observation instead).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.normals._fast_kernels import nearfield_batch, shared_batch, shared_factors
from pipeline.normals.result import COND_CAP, NormalResult

__all__ = ["NearFieldFast", "PlaneBatch", "frame_planes_np", "split_into", "run_split", "BLOCK"]

#: Pixels per block: the block's accumulators (4 G planes) and light rows stay in L1/L2.
BLOCK = 512


_POOLS: dict = {}  # threads -> FramePool, kept for the process (a live loop calls per frame)


def run_split(fn, M: int, threads: int = 1) -> None:
    """``fn(start, stop)`` over ``[0, M)`` in ``threads`` contiguous parts, in parallel (``fn``
    must release the GIL: a ``nogil`` Numba kernel). Parts are multiples of :data:`BLOCK`
    (:meth:`pipeline.base.frame_pool.FramePool.split`)."""
    threads = max(1, int(threads))
    if threads == 1 or M <= BLOCK:
        fn(0, M)
        return
    pool = _POOLS.get(threads)
    if pool is None:
        from pipeline.base.frame_pool import FramePool

        pool = _POOLS.setdefault(threads, FramePool(threads))
    pool.split(fn, M, multiple=BLOCK)


def frame_planes_np(frames: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
    """Frames ``(P, H, W, C)`` as contiguous observation planes ``(P * C, H * W)`` (pattern-major,
    channel-minor), same dtype; ``index`` keeps only those pixels (``(M,)`` flat indices).

    Examples
    --------
    >>> f = np.arange(2 * 1 * 2 * 3, dtype=np.uint8).reshape(2, 1, 2, 3)
    >>> frame_planes_np(f).tolist()
    [[0, 3], [1, 4], [2, 5], [6, 9], [7, 10], [8, 11]]
    """
    a = np.asarray(frames)
    P, H, W, C = a.shape
    planes = np.empty((P * C, H * W), a.dtype)
    split_into(a, planes, 0, H * W)
    return planes if index is None else np.ascontiguousarray(planes[:, index])


def split_into(frames: np.ndarray, planes: np.ndarray, start: int, stop: int) -> None:
    """Pixels ``start:stop`` of frames ``(P, H, W, C)`` into ``planes[:, start:stop]`` (``planes``
    ``(P * C, H * W)``, same dtype), in place (splitting into new arrays and copying them took
    ~2.5x as long: 0.26 against 0.10 ms for 8 RGB frames at 320 x 240)."""
    P, H, W, C = frames.shape
    n = stop - start
    if frames.dtype in (np.uint8, np.uint16, np.float32) and 1 < C <= 4 and frames.flags.c_contiguous:
        import cv2  # SIMD de-interleave (~3x numpy's transposing copy), written into the planes

        for p in range(P):
            src = frames[p].reshape(H * W, 1, C)[start:stop]
            dst = [planes[p * C + c, start:stop].reshape(n, 1) for c in range(C)]
            out = cv2.split(src, dst)
            for d, o in zip(dst, out):
                if o.ctypes.data != d.ctypes.data:  # OpenCV reallocated instead of writing in place
                    d[...] = o.reshape(d.shape)
    else:
        planes[:, start:stop] = frames.reshape(P, H * W, C)[:, start:stop].transpose(0, 2, 1).reshape(P * C, n)


def blocked(a: np.ndarray) -> np.ndarray:
    """``(..., M)`` -> ``(ceil(M / BLOCK), ..., BLOCK)`` float32, zero-padded: each block's data is
    one contiguous run, read as one stream (the per-plane layout made ~100 streams per block,
    more than the prefetchers follow: 3x slower once the field no longer fits the cache)."""
    M = a.shape[-1]
    nb = -(-M // BLOCK)
    pad = np.zeros(a.shape[:-1] + (nb * BLOCK,), np.float32)
    pad[..., :M] = a
    return np.ascontiguousarray(np.moveaxis(pad.reshape(a.shape[:-1] + (nb, BLOCK)), -2, 0))


@dataclass
class PlaneBatch:
    """Normals of ``K`` frames as whole-frame planes: what :meth:`NearFieldFast.solve_batch`
    writes and :meth:`pipeline.depth.fast.FastDST.integrate_batch` reads.

    Attributes
    ----------
    normals : ndarray, shape (K, 3, H, W), float32
    albedo : ndarray, shape (K, G, H, W), float32
    residual : ndarray, shape (K, H, W), float32
    mask : ndarray, shape (K, H, W), bool
    condition : ndarray, shape (H, W), float32
        The same for every frame (it depends on the lights only).
    count : ndarray, shape (H, W), int32
    meta : dict
    """

    normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    mask: np.ndarray
    condition: np.ndarray
    count: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.normals.shape[0])

    def result(self, k: int) -> NormalResult:
        """Frame ``k`` as a :class:`~pipeline.normals.result.NormalResult` (views of the planes)."""
        return NormalResult(normals=np.moveaxis(self.normals[k], 0, -1), albedo=np.moveaxis(self.albedo[k], 0, -1),
                            residual=self.residual[k], condition=self.condition, mask=self.mask[k], count=self.count,
                            meta=dict(self.meta))


class NearFieldFast:
    """Near-field photometric stereo with everything that depends on the lights precomputed.

    Parameters
    ----------
    lights : ndarray, shape (N, H, W, 3)
        Per-pixel light vectors of the ``N = P * C`` observations (pattern-major,
        channel-minor), e.g. a calibration's ``light_field (P, C, H, W, 3)`` reshaped.
    groups : ndarray, shape (N,), optional
        Albedo group (camera channel) of each observation; default: one group.
    flat_field : ndarray, shape (N, H, W), optional
        Observations are divided by it first (where positive; elsewhere the pixel is invalid).
    max_condition : float
        Pixels with a worse-conditioned light matrix are masked.
    albedo_iterations : int, optional
        Per-group albedo alternation steps; None: as :class:`NearFieldSolver` decides (3 when
        the channels see different lights, else 0).
    mask : ndarray, shape (H, W), bool, optional
        Solve only these pixels (the rest come back invalid).
    dark : ndarray, shape (H, W, C), optional
        Dark frame subtracted from every pattern.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> L = rng.normal(size=(6, 2, 3, 3)); L[..., 2] = np.abs(L[..., 2]) + 2
    >>> n = np.array([0.0, 0.6, 0.8])
    >>> I = np.clip(np.einsum("nhwk,k->nhw", L, n) * 40, 0, 255).round().astype(np.uint8)
    >>> fast = NearFieldFast(L)
    >>> res = fast.solve(I.reshape(6, 2, 3, 1))   # (P, H, W, C) frames, here C = 1
    >>> bool(res.mask.all()), float(np.abs(res.normals - n).max()) < 0.02
    (True, True)
    """

    def __init__(self, lights, *, groups=None, flat_field=None, max_condition: float = 1e3,
                 albedo_iterations: int | None = None, mask=None, dark=None):
        L = np.asarray(lights, np.float64)
        if L.ndim != 4 or L.shape[-1] != 3:
            raise ValueError(f"NearFieldFast: lights must have shape (N_obs, H, W, 3), got {L.shape}")
        N, H, W, _ = L.shape
        self.n_obs, self.shape = N, (H, W)
        self.groups = np.zeros(N, np.int64) if groups is None else np.asarray(groups, np.int64)
        if self.groups.shape != (N,) or self.groups.min() < 0:
            raise ValueError(f"NearFieldFast: groups must be ({N},) non-negative integers, got {self.groups.shape}")
        self.num_groups = int(self.groups.max()) + 1
        self.max_condition = float(max_condition)
        full = np.ones((H, W), bool) if mask is None else np.asarray(mask, bool)
        if full.shape != (H, W):
            raise ValueError(f"NearFieldFast: mask must have shape {(H, W)}, got {full.shape}")
        self.region = None if mask is None else full
        self.index = np.flatnonzero(full.ravel()).astype(np.int64)
        Lm = L.reshape(N, H * W, 3)[:, self.index]  # (N, M, 3)
        finite = np.isfinite(Lm).all(axis=(0, 2))
        Lm = np.where(np.isfinite(Lm), Lm, 0.0)
        # Per-group Gram matrices (float64), their sum's inverse and condition number.
        Qg = np.stack([np.einsum("kmi,kmj->mij", Lm[self.groups == g], Lm[self.groups == g])
                       for g in range(self.num_groups)])  # (G, M, 3, 3)
        A = Qg.sum(0)
        det = np.linalg.det(A)
        invertible = np.isfinite(det) & (det != 0)
        inv = np.zeros_like(A)
        inv[invertible] = np.linalg.inv(A[invertible])
        ev = np.linalg.eigvalsh(A)  # ascending
        with np.errstate(divide="ignore", invalid="ignore"):
            cond = np.sqrt(np.clip(ev[:, 2] / np.where(ev[:, 0] > 0, ev[:, 0], 1.0), 1.0, None))
        bad = (ev[:, 0] <= 0) | (ev[:, 2] <= 0) | ~np.isfinite(cond)
        self.condition_m = np.where(bad, COND_CAP, np.minimum(cond, COND_CAP)).astype(np.float32)
        sym = [0, 1, 2, 4, 5, 8]  # xx, xy, xz, yy, yz, zz of a symmetric 3x3
        self.inv = blocked(inv.reshape(-1, 9)[:, sym].T)  # (nb, 6, 512): the inverse is symmetric too
        scale = self._shared_scale(Lm)
        counts = np.bincount(self.groups, minlength=self.num_groups)
        if albedo_iterations is None:
            from pipeline.normals._lstsq import channels_share_lights

            shared = channels_share_lights(Lm, [np.flatnonzero(self.groups == g) for g in range(self.num_groups)])
            albedo_iterations = 0 if shared or (counts < 3).any() else 3
        self.iterations = int(albedo_iterations) if self.num_groups > 1 else 0
        # White patterns (channels share their lights, no alternation): the pseudo-inverse
        # kernel (pipeline.normals._fast_kernels.shared_batch), which reads fewer bytes and vectorises.
        self.pinv = scale is not None and self.iterations == 0
        if self.pinv:
            L0 = Lm[::self.num_groups]  # (P, M, 3): the first channel's lights
            Q0 = np.einsum("kmi,kmj->mij", L0, L0)
            Pi = shared_factors(L0, Q0, invertible)
            self.Lt = blocked(Pi.transpose(0, 2, 1))  # (nb, P, 3, 512): Q_0^-1 L_p
            self.Q = blocked(Q0.reshape(-1, 9)[:, sym].T)  # (nb, 6, 512)
            self.inv = np.zeros((0, 0, 0), np.float32)  # folded into Pi; scale: below, with the validity
        elif scale is None:
            self.Lt = blocked(Lm.transpose(0, 2, 1))  # (nb, N, 3, 512)
            self.Q = blocked(Qg.reshape(self.num_groups, -1, 9)[:, :, sym].transpose(0, 2, 1))  # (nb, G, 6, 512)
            self.scale = np.zeros((0, 0, 0), np.float32)
        else:
            L0 = Lm[::self.num_groups]  # (P, M, 3): the first channel's lights
            Q0 = np.einsum("kmi,kmj->mij", L0, L0).reshape(-1, 9)[:, sym]
            self.Lt = blocked(L0.transpose(0, 2, 1))  # (nb, P, 3, 512)
            self.Q = blocked(Q0.T[None])  # (nb, 1, 6, 512)
            self.scale = blocked(scale)  # (nb, G, 512)
        self.shared = scale is not None
        self.valid0 = finite & invertible & (self.condition_m <= self.max_condition) & (N >= 3)
        M = len(self.index)
        if flat_field is not None:
            f = np.asarray(flat_field, np.float64).reshape(N, H * W)[:, self.index]
            self.valid0 &= (f > 0).all(axis=0)
            self.invflat = blocked(np.where(f > 0, 1.0 / np.where(f > 0, f, 1.0), 0.0))
        else:
            self.invflat = np.zeros((0, 0, 0), np.float32)  # absent: the kernel skips it
        if self.pinv:  # the validity folded into the scalars: the kernel reads no mask
            self.scale = blocked(np.where(self.valid0, scale, 0.0))
        self._count = np.full(M, N, np.int32)  # every observation is used: the same every frame
        self._count.flags.writeable = False  # shared by every result (as the condition map)
        # The two per-pixel maps that do not change between frames, as images once: every
        # result shares them (a region's fill is built here, not per frame).
        self._condition_image = self._full(self.condition_m, COND_CAP)
        self._count_image = self._full(self._count, 0)
        for a in (self._condition_image, self._count_image):
            a.flags.writeable = False
        self.set_dark(dark)

    def _shared_scale(self, Lm: np.ndarray, rtol: float = 2e-7):
        """``scale (G, M)`` when every channel's lights are, at every pixel, one scalar times the
        first channel's to float32 rounding (white patterns: the channels see the same LEDs),
        observations being pattern-major and channel-minor; else None."""
        G, N = self.num_groups, self.n_obs
        if G < 2 or N % G or not np.array_equal(self.groups, np.tile(np.arange(G), N // G)):
            return None
        L = Lm.reshape(N // G, G, -1, 3)  # (P, G, M, 3)
        ref = L[:, 0]
        den = np.einsum("pmi,pmi->m", ref, ref)
        scale = np.ones((G, Lm.shape[1]))
        for g in range(1, G):
            a = np.einsum("pmi,pmi->m", L[:, g], ref) / np.where(den > 0, den, 1.0)
            err = np.abs(L[:, g] - a[None, :, None] * ref).max(axis=(0, 2))
            if (err > rtol * np.abs(L[:, g]).max(axis=(0, 2)) + 1e-30).any():
                return None
            scale[g] = a
        return scale

    def set_dark(self, dark) -> None:
        """Subtract ``dark (H, W, C)`` (None: nothing) from every later frame."""
        N = self.n_obs
        if dark is None:
            self.dark = np.zeros((0, 0, 0), np.float32)  # absent: the kernel skips it
            return
        d = np.asarray(dark, np.float32)
        H, W = self.shape
        C = d.shape[-1]
        if d.shape != (H, W, C) or N % C:
            raise ValueError(f"NearFieldFast: dark must be (H, W, C) = ({H}, {W}, C) with C dividing {N}, got {d.shape}")
        planes = frame_planes_np(np.broadcast_to(d, (N // C, H, W, C)).copy(), self.index)
        self.dark = blocked(planes.astype(np.float32))

    @property
    def pixels(self) -> int:
        return int(len(self.index))

    def solve(self, frames, threads: int = 1) -> NormalResult:
        """Normals of one frame set ``(P, H, W, C)`` (uint8 or uint16; ``P * C = N``), its pixels
        split between ``threads`` threads (the kernel releases the GIL; a frame this small is
        memory-bound, so two threads gain what the second core's share of the memory bandwidth
        gives). Normals and albedo are views of the kernel's planes, which
        :class:`pipeline.depth.fast.FastDST` reads without a split."""
        f = self._check(np.asarray(frames)[None], "solve")
        out = self.batch_planes(1)
        kernel, args, outs = self._call(f, out)
        run_split(lambda a, b: kernel(*args, a, b, *outs), len(self.index), threads)
        return out.result(0)

    def batch_planes(self, K: int) -> PlaneBatch:
        """Output planes for :meth:`solve_batch` of ``K`` frames (pixels outside the region filled
        here: the kernels write only the region's)."""
        H, W = self.shape
        G = self.num_groups
        out = PlaneBatch(np.empty((K, 3, H, W), np.float32), np.empty((K, G, H, W), np.float32),
                         np.empty((K, H, W), np.float32), np.empty((K, H, W), np.bool_),
                         self._condition_image, self._count_image,
                         {"solver": "nearfield", "method": "fast", "max_condition": self.max_condition})
        if self.region is not None:
            out.normals[:, :2] = 0.0
            out.normals[:, 2] = 1.0
            out.albedo[...] = 0.0
            out.residual[...] = 0.0
            out.mask[...] = False
        return out

    def solve_batch(self, frames, pool=None, out: PlaneBatch | None = None, parts: int | None = None) -> PlaneBatch:
        """Normals of ``K`` frame sets ``frames (K, P, H, W, C)`` (uint8 or uint16, C-contiguous as a
        camera or an HDF5 file gives them; ``P * C = N``) by one call of the kernel per part
        (:func:`pipeline.normals._fast_kernels.shared_batch` / ``nearfield_batch``): each part is a
        run of pixels of every frame, so a block's factors are read once a call.

        ``pool``: a :class:`pipeline.base.frame_pool.FramePool` whose threads run the parts
        (None: this thread); ``parts``: how many (default one a thread, in whole blocks as equal
        as they come: 150 blocks of 320 x 240 on 16 threads are runs of 9 and 10);
        ``out``: planes to fill (:meth:`batch_planes`), else new ones. The
        same numbers as :meth:`solve` frame by frame, bit for bit.
        """
        f = self._check(np.asarray(frames), "solve_batch")
        out = self.batch_planes(f.shape[0]) if out is None else out
        kernel, args, outs = self._call(f, out)
        M = len(self.index)
        if pool is None:
            kernel(*args, 0, M, *outs)
        else:
            pool.split(lambda a, b: kernel(*args, a, b, *outs), M, multiple=BLOCK, parts=parts)
        return out

    def _check(self, f: np.ndarray, name: str) -> np.ndarray:
        """Frames ``(K, P, H, W, C)`` checked (C-contiguous)."""
        if f.ndim != 5 or f.shape[2:4] != self.shape or f.shape[1] * f.shape[4] != self.n_obs:
            got, want = (f.shape[1:], "(P, {}, {}, C)") if name == "solve" else (f.shape, "(K, P, {}, {}, C)")
            raise ValueError(f"NearFieldFast.{name}: frames must be {want.format(*self.shape)} with P * C = "
                             f"{self.n_obs}, got {got}")
        if f.dtype.kind not in "ui":
            raise ValueError(f"NearFieldFast.{name}: integer frames expected (uint8/uint16), got {f.dtype}; float "
                             f"frames go to the eager NearFieldSolver")
        return np.ascontiguousarray(f)

    def _call(self, f: np.ndarray, out: PlaneBatch):
        """``(kernel, arguments, outputs)`` of the kernel on frames ``f (K, P, H, W, C)``; the pixel
        range goes between the arguments and the outputs."""
        K, P, H, W, C = f.shape
        if out.normals.shape != (K, 3, H, W) or out.albedo.shape[1] != self.num_groups:
            raise ValueError(f"NearFieldFast: output planes are for {out.normals.shape}, frames {f.shape}")
        flat = f.reshape(K, P, H * W * C)
        index = self.index if self.region is not None else np.zeros(0, np.int64)
        outs = (out.normals.reshape(K, 3, H * W), out.albedo.reshape(K, self.num_groups, H * W),
                out.residual.reshape(K, H * W), out.mask.reshape(K, H * W))
        if self.pinv:
            return shared_batch, (flat, index, C, self.dark, self.invflat, self.Lt, self.Q, self.scale), outs
        return nearfield_batch, (flat, index, C, self.dark, self.invflat, self.Lt, self.inv, self.Q, self.scale,
                                 self.groups, self.num_groups, self.valid0, self.iterations), outs

    def _full(self, a, fill):
        """Per-pixel values of the solved pixels ``(M, ...)`` as an image ``(H, W, ...)``."""
        H, W = self.shape
        if self.region is None:
            return a.reshape((H, W) + a.shape[1:])
        out = np.empty((H * W,) + a.shape[1:], a.dtype)
        out[...] = fill
        out[self.index] = a
        return out.reshape((H, W) + a.shape[1:])
