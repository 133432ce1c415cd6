"""Figures of merit of a lens design, measured by tracing it with common random numbers.

:class:`Evaluator` traces a candidate scene (every LED by hit rotation, :func:`sim.optics.multisource.trace_all`)
onto a coarse grid over its imaging plane, always with the same rays (same sampler, count
and seed for every candidate: common random numbers, so two designs differ by their optics,
not by their Monte Carlo noise), and returns :class:`Metrics`:

``fraction_on_screen``  fraction of the LEDs' power landing on the imaging plane (the paper's figure);
``uniformity_cv``       coefficient of variation of the 24-LED white flat-gel image over the whole plane
                        (as ``iristac sim trace`` reports it, on the coarse grid);
``channel_cv``          per-channel uniformity after channel separation for lighting modes: the worst
                        CV over every lit (frame, camera channel) of the modes' flat-gel images,
                        over the gel's active area (:func:`sim.uniformity.central_disc`);
``valid_fraction``      photometric stereo: the fraction of active-area pixels whose per-pixel light
                        matrix for the modes (every frame and channel, ``sim.illumination_model.light_matrices``)
                        has condition number ``<= max_condition`` (the solvers' mask, 1e3 by default);
                        the worst over the modes;
``median_condition``    the median of that condition number over the active area (worst mode).

:data:`OBJECTIVES` maps each objective name to the metric and its sense; :func:`loss`
turns metrics into the number the optimizers minimise, with metric constraints.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass

import numpy as np

from sim.optics.grid import PixelGrid
from sim.optics.multisource import trace_all
from sim.scene import Scene

__all__ = ["Metrics", "Evaluator", "OBJECTIVES", "CONSTRAINTS", "BARE_MARGIN", "bare_limit", "loss",
           "constraint_violations",
           "condition_numbers", "coarse_grid"]

#: objective name -> (metric, +1 to maximise / -1 to minimise)
OBJECTIVES = {
    "flux": ("fraction_on_screen", +1),
    "cv": ("uniformity_cv", -1),
    "channel-cv": ("channel_cv", -1),
    "valid": ("valid_fraction", +1),
    "condition": ("median_condition", -1),
}

#: constraint name -> (metric, "min" or "max" bound)
CONSTRAINTS = {
    "min_flux": ("fraction_on_screen", "min"),
    "max_cv": ("uniformity_cv", "max"),
    "max_channel_cv": ("channel_cv", "max"),
    "min_valid": ("valid_fraction", "min"),
    "max_median_condition": ("median_condition", "max"),
}


#: How much better than the bare LEDs a ``"bare"`` constraint asks for (relative): "beats the bare
#: LEDs" means by more than the search's Monte Carlo noise, not by a tie (a lens that no ray
#: meets ties the bare LEDs exactly).
BARE_MARGIN = 0.01


def bare_limit(name: str, bare: Metrics) -> float:
    """The bound a ``"bare"`` constraint ``name`` stands for, given the bare LEDs' metrics.

    Examples
    --------
    >>> m = Metrics(fraction_on_screen=0.3, uniformity_cv=0.2, valid_fraction=1.0, median_condition=4.0)
    >>> round(bare_limit("min_flux", m), 6), round(bare_limit("max_cv", m), 6), bare_limit("min_valid", m)
    (0.303, 0.198, 1.0)
    """
    metric, kind = CONSTRAINTS[name]
    v = getattr(bare, metric)
    if metric == "valid_fraction":
        return v  # a fraction that may be 1 already: no worse than bare
    return v * (1.0 + BARE_MARGIN) if kind == "min" else v * (1.0 - BARE_MARGIN)


@dataclass
class Metrics:
    """What one trace of a design measured (``None``: not asked for)."""

    fraction_on_screen: float
    uniformity_cv: float
    channel_cv: float | None = None
    valid_fraction: float | None = None
    median_condition: float | None = None
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


def coarse_grid(scene: Scene, rows: int) -> PixelGrid:
    """A ``rows``-row pixel grid over the scene's whole imaging plane (square pixels where the plane allows).

    Examples
    --------
    >>> from sim.scene import load_scene
    >>> g = coarse_grid(load_scene("default"), 40)
    >>> g.shape, g.pitch
    ((40, 40), (1.5, 1.5))
    """
    w, h = scene.plane.size
    cols = max(1, round(rows * w / h))
    return PixelGrid((int(rows), int(cols)), (h / rows, w / cols), float(scene.plane.z))


def condition_numbers(V: np.ndarray, drive: np.ndarray) -> np.ndarray:
    """Per-pixel condition number (H, W) of the light matrix of patterns ``drive`` (P, L, 3).

    ``V`` (L, H, W, 3) is the vector irradiance per LED. The light matrix of a pixel stacks
    ``L_pj = sum_i W_p[i, j] V_i`` over patterns ``p`` and camera channels ``j`` (``(P*3, 3)``,
    unlit channels are zero rows and change nothing); its condition number is the ratio of its
    largest to smallest singular value (``inf`` where it is rank-deficient). Orthogonal frame
    changes keep singular values, so the optical frame serves.

    Examples
    --------
    Three orthogonal unit lights: perfectly conditioned.

    >>> V = np.zeros((3, 1, 1, 3)); V[0, ..., 0] = V[1, ..., 1] = V[2, ..., 2] = 1.0
    >>> drive = np.zeros((3, 3, 3)); drive[[0, 1, 2], [0, 1, 2], :] = 1.0
    >>> float(condition_numbers(V, drive)[0, 0])
    1.0
    """
    V = np.asarray(V, dtype=np.float64)
    L = np.einsum("plj,lhwk->hwpjk", np.asarray(drive, dtype=np.float64), V)
    H, W = V.shape[1:3]
    A = L.reshape(H * W, -1, 3)
    s = np.linalg.svd(A, compute_uv=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(s[:, -1] > s[:, 0] * 1e-12, s[:, 0] / s[:, -1], np.inf)
    return cond.reshape(H, W)


class Evaluator:
    """Trace designs with common random numbers and measure their :class:`Metrics`.

    Parameters
    ----------
    rays : int
        Rays per design (LED 0's, binned for every LED by hit rotation).
    sampler, seed : str, int
        Ray sampler and seed, the same for every design (common random numbers).
    grid : int
        Rows of the coarse grid over the imaging plane (the CV of a 300 x 300 image from 1e5 rays
        would measure Monte Carlo noise rather than the design).
    modes : sequence of str or LightingMode
        Lighting modes of ``channel_cv``, ``valid_fraction`` and ``median_condition`` (none:
        those stay ``None`` and the trace bins no vector field).
    max_condition : float
        Condition number up to which a pixel's light matrix counts as well conditioned.
    region : float
        Active area: the centred disc of this fraction of the grid's smaller side.
    device, dtype, engine, threads
        How to trace (:func:`sim.optics.multisource.trace_all`; default: the compiled kernel).

    Examples
    --------
    >>> from sim.scene import load_scene
    >>> ev = Evaluator(rays=4096, grid=10, modes=["trichromatic"])
    >>> m = ev(load_scene("default"))
    >>> 0.0 < m.fraction_on_screen < 1.0, m.valid_fraction is not None
    (True, True)
    """

    def __init__(self, *, rays: int = 100_000, sampler: str = "sobol", seed: int = 0, grid: int = 40,
                 modes=(), max_condition: float = 1e3, region: float = 0.9, device="cpu", dtype=None,
                 engine: str | None = None, threads: int | None = None):
        from pipeline.base.modes import load_mode, mode_drive

        self.rays, self.sampler, self.seed, self.grid = int(rays), sampler, int(seed), int(grid)
        self.modes = [load_mode(m) for m in modes]
        self.drives = [mode_drive(m) for m in self.modes]
        self.max_condition = float(max_condition)
        self.region = float(region)
        self.device, self.dtype, self.engine, self.threads = device, dtype, engine, threads

    @property
    def vector(self) -> bool:
        return bool(self.modes)

    def __call__(self, scene: Scene) -> Metrics:
        from sim.uniformity import central_disc

        t0 = time.perf_counter()
        g = coarse_grid(scene, self.grid)
        r = trace_all(scene, g, rays=self.rays, sampler=self.sampler, seed=self.seed, vector=self.vector,
                      device=self.device, dtype=self.dtype, engine=self.engine, threads=self.threads)
        E = r.E[0].astype(np.float64)  # (L, h, w)
        rgb = np.asarray(scene.leds.rgb, dtype=np.float64)
        white = np.einsum("lhw,lj->hw", E, rgb) / 3.0
        mean = float(white.mean())
        cv = float(white.std() / mean) if mean > 0 else math.inf
        m = Metrics(fraction_on_screen=float(np.mean(r.fraction_on_grid)), uniformity_cv=cv)
        if self.modes:
            region = central_disc(g.shape, self.region)
            ccv, valid, med = 0.0, 1.0, 0.0
            for drive in self.drives:
                if drive.shape[1] != E.shape[0]:
                    raise ValueError(f"Evaluator: a mode drives {drive.shape[1]} LEDs, the scene has {E.shape[0]}")
                imgs = np.einsum("plj,lhw->pjhw", drive, E)[..., region]  # (P, 3, pixels)
                means = imgs.mean(-1)
                lit = means > 0
                cvs = np.where(lit, imgs.std(-1) / np.where(lit, means, 1.0), 0.0)
                ccv = max(ccv, float(cvs.max()) if lit.any() else math.inf)
                cond = condition_numbers(r.V[0], drive)[region]
                valid = min(valid, float(np.mean(cond <= self.max_condition)))
                med = max(med, float(np.median(cond)))
            m.channel_cv, m.valid_fraction, m.median_condition = ccv, valid, med
        m.seconds = time.perf_counter() - t0
        return m


def constraint_violations(metrics: Metrics, limits: dict) -> dict:
    """Relative violation (>= 0) of each metric constraint in ``limits`` (name -> bound)."""
    out = {}
    for name, bound in limits.items():
        if bound is None:
            continue
        metric, kind = CONSTRAINTS[name]
        v = getattr(metrics, metric)
        if v is None:
            raise ValueError(f"constraint {name} needs {metric}, which this evaluation did not measure "
                             f"(give lighting modes)")
        scale = max(abs(float(bound)), 1e-9)
        miss = (float(bound) - v) if kind == "min" else (v - float(bound))
        out[name] = max(0.0, miss / scale) if math.isfinite(miss) else 1e6
    return out


def _objective_value(metrics: Metrics, objective: str) -> float:
    metric, sense = OBJECTIVES[objective]
    v = getattr(metrics, metric)
    if v is None:
        raise ValueError(f"objective {objective!r} needs {metric}, which this evaluation did not measure "
                         f"(give lighting modes)")
    if metric == "median_condition":
        v = math.log10(v) if v > 0 and math.isfinite(v) else 12.0  # decades, capped like the solvers
    return -sense * float(v)


#: A loss no traced design reaches, per objective (designs that are not traced rank above it).
_WORST = {"flux": 0.0, "cv": 100.0, "channel-cv": 100.0, "valid": 0.0, "condition": 12.0}

#: Weight of the metric constraints' relative violation in the loss of an infeasible design.
PENALTY = 5.0


def loss(metrics: Metrics | None, objective: str, limits: dict, geometry_violation: float = 0.0) -> tuple[float, bool]:
    """``(loss, feasible)``: the number the optimizers minimise.

    A traced design scores its objective (negated where it is maximised; the median condition
    in decades) plus :data:`PENALTY` times its relative violation of the metric constraints
    (a soft penalty: the search may cross an infeasible region toward a better feasible one;
    only feasible designs can win, :func:`sim.lensopt.search.run_search` keeps the best of
    those). A design that misses the manufacturing limits or does not close into a lens is not
    traced (``metrics`` None) and scores above every traced design, by its miss in mm.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}; expected one of {', '.join(OBJECTIVES)}")
    if metrics is None or geometry_violation > 0:
        return _WORST[objective] + 1e7 + float(geometry_violation), False
    total = sum(constraint_violations(metrics, limits).values())
    return _objective_value(metrics, objective) + PENALTY * total, total == 0
