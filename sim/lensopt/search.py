"""Searching the design space: Nelder-Mead (the default), CMA-ES and uniform random search.

A :class:`Problem` turns a point of the unit cube into a scored :class:`Candidate`: decode the
design, check the manufacturing limits (a design that misses them, or does not close into a
lens, is scored without tracing), trace it with the evaluator's common random numbers, and
score it with :func:`sim.lensopt.objectives.loss`. :func:`run_search` drives one of
:data:`METHODS` for a budget of evaluations (and optionally seconds) and records the
trajectory: the loss and the best feasible objective after every evaluation, against the
evaluation count and the wall time.

Why derivative-free, and why Nelder-Mead by default (measured by ``iristac bench lens``, see
``docs/simulator.md``): the traced objective is piecewise constant at small scales (a ray
crossing a pixel or screen edge, a ray switching between missing and entering the lens), so
finite-difference derivatives at 0.001 mm steps disagree in size and even sign with those at
0.1-1 mm, and a smoothed differentiable tracer would need smooth binning, smooth silhouettes
and smooth TIR, each a bias of its own. With common random numbers the objective is
deterministic; on both shipped briefs (6 and 7 parameters, 600 designs, 4 seeds) Nelder-Mead
(scipy, restarted from the best point with a fresh simplex while budget remains) found better
designs on average than CMA-ES (the ``cma`` package, IPOP restarts) at either initial step,
and both far better than uniform random search. End to end CMA-ES gave the better confirmed
design on the default scene's brief, which therefore names it (a brief's ``method``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from pipeline.base.errors import UserError
from sim.lensopt.constraints import Manufacturing, violations
from sim.lensopt.objectives import OBJECTIVES, Evaluator, Metrics, loss
from sim.lensopt.space import DesignSpace

__all__ = ["METHODS", "Candidate", "Problem", "Trajectory", "run_search"]

METHODS = ("nelder-mead", "cmaes", "random")


@dataclass
class Candidate:
    """One evaluated design."""

    design: dict
    loss: float
    feasible: bool
    metrics: Metrics | None = None
    geometry: dict = field(default_factory=dict)
    note: str = ""

    def objective_value(self, objective: str) -> float | None:
        """The objective's metric (not the loss), None if not traced."""
        if self.metrics is None:
            return None
        return getattr(self.metrics, OBJECTIVES[objective][0])


class Problem:
    """Score designs: manufacturing limits, then a trace with common random numbers, then the loss."""

    def __init__(self, space: DesignSpace, evaluator: Evaluator, objective: str, limits: dict,
                 manufacturing: Manufacturing):
        if objective not in OBJECTIVES:
            raise UserError(f"optimize-lens: unknown objective {objective!r}; expected one of {', '.join(OBJECTIVES)}")
        self.space, self.evaluator, self.objective = space, evaluator, objective
        self.limits = dict(limits)
        self.manufacturing = manufacturing.resolved(space.base)
        self.count = 0
        self.traced = 0

    def evaluate_design(self, design: dict) -> Candidate:
        self.count += 1
        try:
            scene = self.space.scene(design)
        except (UserError, ValueError) as exc:
            # Does not close into a lens (or puts an LED inside it): the worst kind of miss.
            return Candidate(design, loss(None, self.objective, self.limits, 1e3)[0], False, note=str(exc))
        geo = violations(scene, self.manufacturing)
        g = sum(geo.values())
        if g > 0:
            return Candidate(design, loss(None, self.objective, self.limits, g)[0], False, geometry=geo,
                             note="misses " + ", ".join(k for k, v in geo.items() if v > 0))
        m = self.evaluator(scene)
        self.traced += 1
        value, ok = loss(m, self.objective, self.limits)
        return Candidate(design, value, ok, metrics=m, geometry=geo)

    def evaluate(self, u) -> Candidate:
        return self.evaluate_design(self.space.decode(u))


@dataclass
class Trajectory:
    """Per evaluation: elapsed seconds, loss, feasibility, the objective (feasible designs) and
    the best feasible objective so far."""

    seconds: list = field(default_factory=list)
    loss: list = field(default_factory=list)
    feasible: list = field(default_factory=list)
    values: list = field(default_factory=list)
    best_value: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"evaluations": len(self.loss), "seconds": self.seconds, "loss": self.loss,
                "feasible": self.feasible, "values": self.values, "best_value": self.best_value}


class _Budget(Exception):
    pass


def run_search(problem: Problem, start: dict, *, method: str = "nelder-mead", evaluations: int = 600,
               seconds: float | None = None, seed: int = 0, sigma0: float = 0.25, popsize: int | None = None,
               progress: bool = True) -> tuple[Candidate, Candidate, Trajectory]:
    """Search from ``start`` for at most ``evaluations`` designs (and ``seconds``).

    Returns ``(best, start_candidate, trajectory)``; ``best`` is the lowest-loss design seen
    (feasible if any was). Nelder-Mead restarts from the best design with a fresh simplex
    (``sigma0`` per axis) and CMA-ES with a doubled population (IPOP) when they converge before
    the budget is spent.
    """
    from tqdm.auto import tqdm

    if method not in METHODS:
        raise UserError(f"optimize-lens: unknown method {method!r}; expected one of {', '.join(METHODS)}")
    if evaluations < 1:
        raise UserError(f"optimize-lens: evaluations must be >= 1, got {evaluations}")
    traj = Trajectory()
    t0 = time.perf_counter()
    state = {"best": None}
    bar = tqdm(total=evaluations, desc=f"optimize-lens ({method})", unit="design", disable=not progress,
               leave=False, dynamic_ncols=True)
    objective = problem.objective

    def score(u) -> float:
        if len(traj.loss) >= evaluations or (seconds is not None and time.perf_counter() - t0 > seconds):
            raise _Budget
        c = problem.evaluate(u)
        best = state["best"]
        # Feasible beats infeasible; then the lower loss.
        if best is None or (c.feasible, -c.loss) > (best.feasible, -best.loss):
            state["best"] = best = c
        traj.seconds.append(time.perf_counter() - t0)
        traj.loss.append(float(c.loss))
        traj.feasible.append(bool(c.feasible))
        traj.values.append(c.objective_value(objective) if c.feasible else None)
        traj.best_value.append(best.objective_value(objective) if best.feasible else None)
        bar.update(1)
        if best.feasible:
            bar.set_postfix_str(f"best {objective} {best.objective_value(objective):.4g}")
        return float(c.loss)

    u0 = problem.space.encode({k: start[k] for k in problem.space.names})
    rng = np.random.default_rng(seed)
    try:
        score(u0)
        first = state["best"]
        if method == "random":
            while True:
                score(rng.random(len(u0)))
        elif method == "nelder-mead":
            from scipy.optimize import minimize

            # Nelder-Mead on the clipped cube, restarted from the best point while budget remains.
            # It is deterministic: seeds other than 0 start it from a jittered start (sigma0 per axis).
            x = u0 if seed == 0 else np.clip(u0 + sigma0 * rng.standard_normal(len(u0)), 0.0, 1.0)
            while True:
                minimize(lambda u: score(np.clip(u, 0.0, 1.0)), x, method="Nelder-Mead",
                         options={"maxfev": evaluations, "initial_simplex": _simplex(x, sigma0)})
                x = problem.space.encode({k: state["best"].design[k] for k in problem.space.names})
        else:
            _cmaes(score, u0, sigma0, popsize, seed)
    except _Budget:
        pass
    finally:
        bar.close()
    return state["best"], first, traj


def _simplex(x, step):
    x = np.asarray(x, dtype=float)
    pts = [x]
    for i in range(len(x)):
        y = x.copy()
        y[i] = y[i] + step if y[i] + step <= 1.0 else y[i] - step
        pts.append(y)
    return np.array(pts)


def _cmaes(score, u0, sigma0, popsize, seed):
    import cma

    pop = popsize
    run = 0
    while True:
        opts = {"bounds": [0.0, 1.0], "seed": int(seed) * 1000 + run + 1, "verbose": -9, "tolfun": 1e-5,
                "tolx": 1e-4}
        if pop:
            opts["popsize"] = int(pop)
        es = cma.CMAEvolutionStrategy(list(u0), sigma0, opts)
        while not es.stop():
            X = es.ask()
            es.tell(X, [score(x) for x in X])
        # Converged before the budget: restart with twice the population (IPOP-CMA-ES).
        pop = 2 * (pop or es.popsize)
        run += 1
        if not math.isfinite(pop):
            return
