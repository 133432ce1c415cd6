"""The one frame pipeline: integer camera frames to normals, heights (and contact), a run at a time.

``iristac live`` runs it on one frame set at a time, ``reconstruct`` and ``batch`` on chunks of
a recording's frames (:mod:`pipeline.streaming`); every path is the same code:

- the normals: the solver built by :func:`pipeline.solving.frame_solvers.frame_solver`:
   - a fast path that solves many frames in one call (``solve_batch``: the near-field and
     far-field paths, :class:`pipeline.normals.fast.NearFieldFast`): every frame of the chunk
     at once, each thread a run of pixels of every frame;
   - a fast path per frame (the LUT's and the MLP's, :mod:`pipeline.normals.fast_models`):
     frames in parallel, each thread a run of frames, one compiled pass each (a single frame:
     its pixels split over the threads, as live does);
   - the eager solve (:class:`pipeline.normals.solve.FrameSolver`), where no fast path applies:
     the chunk in one call, its own threads (torch's or BLAS's);
- the heights: the integrator's fast path (``dst``: :meth:`pipeline.depth.fast.FastDST.integrate_batch`,
   a run of frames per thread) on the whole frame, else the eager integrator per frame (on the
   region's bounding box where one is given, :func:`pipeline.depth.integrate`), frames in parallel;
- the contact masks (when asked): :func:`pipeline.frame_pipeline.contact.contact_mask` per frame, frames in parallel.

Filled-in marker pixels (``filled``) are integrated through, as the depth stage does.

Examples
--------
>>> from pipeline.normals.fast import NearFieldFast
>>> from pipeline.depth.fast import FastDST
>>> rng = np.random.default_rng(0)
>>> L = rng.normal(size=(6, 8, 8, 3)); L[..., 2] = np.abs(L[..., 2]) + 2
>>> frames = rng.integers(0, 255, size=(4, 6, 8, 8, 1), dtype=np.uint8)   # (K, P, H, W, C)
>>> with FramePipeline(NearFieldFast(L), FastDST((8, 8), 0.1), threads=2) as pipe:
...     out = pipe.run(frames)
>>> out.normals.shape, out.height.shape, out.contact is None
((4, 8, 8, 3), (4, 8, 8), True)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.base.frame_pool import FramePool

__all__ = ["FramePipeline", "FrameBatch"]


@dataclass
class FrameBatch:
    """The results of ``n`` frame sets (arrays over the chunk's frames).

    Attributes
    ----------
    normals : (n, H, W, 3) float32
    mask : (n, H, W) bool
    height : (n, H, W) float32, mm
    height_mask : (n, H, W) bool
    confidence : (n, H, W) float32 or None
        The calibration models' rating of each normal.
    extras : dict
        ``albedo (n, H, W, G)``, ``residual``, ``condition`` ``(n, H, W)`` float32, ``count``
        ``(n, H, W)`` int32, where the solver gives them.
    contact : (n, H, W) bool or None
    meta : list of dict
        Per frame: the solver's scalar facts (``drift_before_dn`` ... where drift was removed).
    """

    normals: np.ndarray
    mask: np.ndarray
    height: np.ndarray
    height_mask: np.ndarray
    confidence: np.ndarray | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    contact: np.ndarray | None = None
    meta: list[dict] = field(default_factory=list)
    #: The near-field fast path's normal planes ``(n, 3, H, W)`` (what the DST reads fastest), or None.
    planes: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.normals.shape[0])


class FramePipeline:
    """Normals, heights and contact of frame sets, a chunk at a time (see the module docstring).

    Parameters
    ----------
    solver : object
        From :func:`pipeline.solving.frame_solvers.frame_solver`: ``solve(frames (P, H, W, C),
        threads)``, ``method`` (``fast``/``eager``); ``solve_batch`` where it has one;
        ``solve_stack`` (the eager one).
    integrator : object
        From :func:`pipeline.depth.frame_integrator` (``integrate(normals, mask)``;
        ``integrate_batch`` on the fast path), or None: no heights (``height`` all 0, invalid).
    threads : int, optional
        The pool's threads (None or 0: every core this process may use).
    region : (H, W) bool, optional
        The solved pixels: the eager integrators integrate on them (the fast ``dst`` on the whole
        frame is then not used).
    filled : (H, W) bool, optional
        Filled-in marker pixels: integrated through.
    contact : callable, optional
        ``contact(frames (P, H, W, C), height (H, W), valid (H, W)) -> (H, W) bool``: the contact
        mask of one frame set (None: none computed).
    extras : tuple of str
        Which of ``albedo``, ``residual``, ``condition``, ``count`` a chunk's results keep
        (:attr:`FrameBatch.extras`; the others are dropped frame by frame).
    """

    def __init__(self, solver, integrator, *, threads: int | None = 1, region=None, filled=None, contact=None,
                 extras: tuple[str, ...] = ()):
        self.solver, self.integrator = solver, integrator
        self.extras = tuple(extras)
        self.pool = FramePool(None if not threads else threads)
        self.threads = self.pool.threads
        self.region = None if region is None else np.asarray(region, bool)
        self.filled = None if filled is None else np.asarray(filled, bool)
        self.contact_fn = contact
        self.batch_normals = hasattr(solver, "solve_batch") and getattr(solver, "method", "") == "fast"
        self.eager_solver = getattr(solver, "method", "") == "eager"
        self.fast_depth = (integrator is not None and hasattr(integrator, "integrate_batch") and self.region is None)
        self._planes = None
        # Two sets of chunk arrays, used in turn: a chunk's results stay valid while the next one
        # is solved (a writer thread has them meanwhile), and a stream of chunks touches no new
        # memory (a new array per chunk cost a page fault per 4 KB of results).
        self._buffers: list[dict] = [{}, {}]
        self._slot = 0

    def _buf(self, name: str, shape: tuple, dtype) -> np.ndarray:
        """The current slot's array ``name`` of ``shape`` and ``dtype`` (kept between chunks)."""
        cache = self._buffers[self._slot]
        a = cache.get(name)
        if a is None or a.shape != tuple(shape) or a.dtype != np.dtype(dtype):
            a = cache[name] = np.empty(shape, dtype)
        return a

    @property
    def method(self) -> str:
        """How frames are solved: ``fast`` or ``eager``."""
        return "eager" if self.eager_solver else "fast"

    def close(self) -> None:
        self.pool.close()

    def __enter__(self) -> FramePipeline:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- one frame set (live) ------------------------------------------------------------------
    def one(self, frames):
        """``(NormalResult, DepthResult)`` of one frame set ``(P, H, W, C)``: its pixels split over
        the threads (live's latency path)."""
        res = self.solver.solve(frames, threads=self.threads)
        if self.integrator is None:
            from pipeline.depth._common import DepthResult

            return res, DepthResult(np.zeros(res.mask.shape, np.float32), np.zeros(res.mask.shape, bool), {})
        usable = res.mask if self.filled is None else (res.mask | self.filled)
        if self.fast_depth:
            return res, self.integrator.integrate(res.normals, usable, workers=self.threads)
        return res, self._integrate_one(res.normals, usable)

    # -- a chunk of frame sets (reconstruct, batch) ----------------------------------------------
    def run(self, frames, normals=None, heights=None) -> FrameBatch:
        """The :class:`FrameBatch` of frame sets ``(n, P, H, W, C)`` (integers for the fast paths).

        ``normals``: ``(normals (n, H, W, 3), mask (n, H, W))`` already solved (read back from a
        store entry): the frames are not solved again; ``heights``: ``(height, valid)`` likewise
        (then only the contact masks are computed). The batch's arrays are the pipeline's own:
        valid until the call after next (copy what you keep longer)."""
        f = np.asarray(frames)
        self._slot ^= 1
        if normals is None:
            out = self._normals(f)
        else:
            n, m = (np.asarray(a) for a in normals)
            out = FrameBatch(n.astype(np.float32, copy=False), m.astype(bool, copy=False),
                             self._buf("height", m.shape, np.float32), self._buf("height_mask", m.shape, np.bool_),
                             meta=[{} for _ in m])
        if heights is None:
            self._heights(out)
        else:
            out.height, out.height_mask = (np.asarray(a) for a in heights)
        if self.contact_fn is not None:
            out.contact = self._buf("contact", out.height.shape, np.bool_)

            def touch(a: int, b: int) -> None:
                for k in range(a, b):
                    out.contact[k] = self.contact_fn(f[k], out.height[k], out.height_mask[k])

            self.pool.split(touch, len(f))
        return out

    def _normals(self, f: np.ndarray) -> FrameBatch:
        n = len(f)
        H, W = f.shape[2:4]
        if self.batch_normals:
            p = self.solver.solve_batch(f, self.pool, out=self._plane_buffer(n))
            normals = self._buf("normals", (n, H, W, 3), np.float32)

            def transpose(a: int, b: int) -> None:
                normals[a:b] = p.normals[a:b].transpose(0, 2, 3, 1)

            self.pool.split(transpose, n)
            extras = {"albedo": p.albedo.transpose(0, 2, 3, 1), "residual": p.residual,
                      "condition": np.broadcast_to(p.condition, (n, H, W)), "count": np.broadcast_to(p.count, (n, H, W))}
            mask = self._buf("mask", (n, H, W), np.bool_)
            mask[...] = p.mask
            return FrameBatch(normals, mask, self._buf("height", (n, H, W), np.float32),
                              self._buf("height_mask", (n, H, W), np.bool_), extras=extras,
                              meta=[dict(_scalars(p.meta)) for _ in range(n)], planes=p.normals)
        if self.eager_solver:
            results = self.solver.solve_stack(f, self.threads)
            out = self._empty(n, H, W, results[0])
            for k, r in enumerate(results):
                self._put(out, k, r)
            return out
        if n == 1:
            r = self.solver.solve(f[0], threads=self.threads)
            out = self._empty(1, H, W, r)
            self._put(out, 0, r)
            return out
        if hasattr(self.solver, "solve_into") and not self.extras:
            return self._solve_into(f)
        first = self.solver.solve(f[0], threads=1)
        out = self._empty(n, H, W, first)
        self._put(out, 0, first)

        def solve(a: int, b: int) -> None:
            for k in range(max(a, 1), b):  # each result copied into the chunk's arrays and dropped
                self._put(out, k, self.solver.solve(f[k], threads=1))

        self.pool.split(solve, n)
        return out

    def _solve_into(self, f: np.ndarray) -> FrameBatch:
        """Frames in parallel, each solved straight into the chunk's arrays (the LUT's and the MLP's
        fast paths: nothing allocated per frame)."""
        n, H, W = f.shape[0], f.shape[2], f.shape[3]
        M = H * W
        out = FrameBatch(self._buf("normals", (n, H, W, 3), np.float32), self._buf("mask", (n, H, W), np.bool_),
                         self._buf("height", (n, H, W), np.float32), self._buf("height_mask", (n, H, W), np.bool_),
                         confidence=self._buf("confidence", (n, H, W), np.float32), meta=[{} for _ in range(n)])
        normals, mask, conf = out.normals.reshape(n, M, 3), out.mask.reshape(n, M), out.confidence.reshape(n, M)

        def solve(a: int, b: int) -> None:
            for k in range(a, b):
                out.meta[k] = _scalars(self.solver.solve_into(f[k], normals[k], mask[k], conf[k], threads=1))

        self.pool.split(solve, n)
        return out

    def _plane_buffer(self, n: int):
        if self._planes is None or len(self._planes) != n:
            self._planes = self.solver.batch_planes(n)
        return self._planes

    def _empty(self, n: int, H: int, W: int, like) -> FrameBatch:
        """A chunk's arrays, shaped as the first result ``like`` says (its confidence, albedo groups)."""
        conf = None if like.confidence is None else self._buf("confidence", (n, H, W), np.float32)
        extras = {name: self._buf(name, (n,) + np.shape(getattr(like, name)), np.asarray(getattr(like, name)).dtype)
                  for name in self.extras}
        return FrameBatch(self._buf("normals", (n, H, W, 3), np.float32), self._buf("mask", (n, H, W), np.bool_),
                          self._buf("height", (n, H, W), np.float32), self._buf("height_mask", (n, H, W), np.bool_),
                          confidence=conf, extras=extras, meta=[{} for _ in range(n)])

    @staticmethod
    def _put(out: FrameBatch, k: int, r) -> None:
        out.normals[k] = r.normals
        out.mask[k] = r.mask
        if out.confidence is not None:
            out.confidence[k] = 0.0 if r.confidence is None else r.confidence
        for name, a in out.extras.items():
            a[k] = getattr(r, name)
        out.meta[k] = dict(_scalars(r.meta))

    def _heights(self, out: FrameBatch) -> None:
        n = len(out)
        usable = out.mask if self.filled is None else (out.mask | self.filled)
        if self.integrator is None:
            out.height[...] = 0.0
            out.height_mask[...] = False
        elif self.fast_depth:
            src = out.normals if out.planes is None else out.planes  # planes: contiguous reads, the same sums
            self.integrator.integrate_batch(src, usable, self.pool, out=(out.height, out.height_mask))
        else:
            def integrate(a: int, b: int) -> None:
                for k in range(a, b):
                    d = self._integrate_one(out.normals[k], usable[k])
                    out.height[k], out.height_mask[k] = d.height, d.mask

            self.pool.split(integrate, n)

    def _integrate_one(self, normals, usable):
        from pipeline.depth import integrate

        pitch = self.integrator.mm_per_px
        name = getattr(self.integrator, "name", "dst")
        return integrate(normals, pitch, usable, method=name, region=self.region)


def _scalars(meta: dict) -> dict:
    return {k: v for k, v in meta.items() if isinstance(v, (str, int, float, bool))}
