"""Run a graph of cached stages: plan what must be recomputed and why, then execute it.

The graph's nodes are :class:`Stage` objects built by the stage modules of
:mod:`pipeline.stages` (``node(...)``); ``iristac run`` hands a config's graph to
:func:`run_stages`.

A stage is computed only when the store has no valid entry for its key; the key covers its
parameters, its version and the keys of the stages it depends on, so a change anywhere
recomputes exactly the stages downstream of it. A per-config *run manifest* remembers the
previous keys and parameters so that ``--dry-run`` can say *why* a stage will run.

Examples
--------
>>> import tempfile, numpy as np
>>> from pipeline.base.store import StageStore, Record
>>> def make_depth(inputs):
...     return Record("depth", {"height": np.zeros((1, 2, 2), np.float32),
...                             "mask": np.ones((1, 2, 2), bool)},
...                   {"integrator": "fc", "mm_per_px": 0.1})
>>> stages = [Stage("depth", 1, {"integrator": "fc"}, [], make_depth)]
>>> store = StageStore(tempfile.mkdtemp())
>>> [r.cached for r in run_stages(stages, store)], [r.cached for r in run_stages(stages, store)]
([False], [True])
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from pipeline.base.errors import UserError
from pipeline.base.store import Record, StageKey, StageStore, StoreError

__all__ = ["Stage", "PlannedStage", "StageResult", "StageFailed", "plan_stages", "run_stages"]


@dataclass
class Stage:
    """One node of the stage graph.

    Attributes
    ----------
    name : str
        Stage name (``calibrate``, ``synthesize``, ``capture``, ``normals``, ``depth``).
    version : int
        Bump when the computation changes, so old entries stop matching.
    params : dict
        Everything that changes the result.
    depends : list of str
        Names of the stages whose outputs this one reads (their keys enter this key).
    compute : callable
        ``compute(inputs: dict[str, Record]) -> Record``.
    extra_inputs : list of str
        Keys of things outside the graph this stage reads (e.g. the content hash of a
        user's capture file).
    """

    name: str
    version: int
    params: Mapping[str, Any]
    depends: Sequence[str]
    compute: Callable[[dict[str, Record]], Record]
    extra_inputs: Sequence[str] = ()
    schema: str | None = None


@dataclass
class PlannedStage:
    stage: Stage
    key: StageKey
    cached: bool
    reason: str


@dataclass
class StageResult:
    """What happened to one stage (``--json`` prints ``name``, ``cached``, ``seconds``, ``key``)."""

    name: str
    cached: bool
    seconds: float
    key: str
    path: str | None = None
    reason: str = ""
    error: str | None = None

    def to_json(self) -> dict:
        d = {"name": self.name, "cached": self.cached, "seconds": round(self.seconds, 4), "key": self.key,
             "path": self.path, "reason": self.reason}
        if self.error:
            d["error"] = self.error
        return d


class StageFailed(UserError):
    """A stage failed; earlier stages' results stay cached. ``results`` holds what ran."""

    def __init__(self, stage: str, error: BaseException, results: list[StageResult]):
        self.stage = stage
        self.error = error
        self.results = results
        super().__init__(f"stage {stage!r} failed: {error}")


def _order(stages: Sequence[Stage]) -> list[Stage]:
    by_name = {s.name: s for s in stages}
    if len(by_name) != len(stages):
        raise ValueError("stage names must be unique")
    done: list[Stage] = []
    seen: set[str] = set()

    def visit(s: Stage, path: tuple[str, ...]):
        if s.name in seen:
            return
        if s.name in path:
            raise ValueError(f"stage graph has a cycle: {' -> '.join(path + (s.name,))}")
        for d in s.depends:
            if d not in by_name:
                raise ValueError(f"stage {s.name!r} depends on unknown stage {d!r}")
            visit(by_name[d], path + (s.name,))
        seen.add(s.name)
        done.append(s)

    for s in stages:
        visit(s, ())
    return done


def _downstream(stages: Sequence[Stage], roots: set[str]) -> set[str]:
    out = set(roots)
    changed = True
    while changed:
        changed = False
        for s in stages:
            if s.name not in out and any(d in out for d in s.depends):
                out.add(s.name)
                changed = True
    return out


def _manifest_path(store: StageStore, run_name: str) -> Path:
    return store.root / "runs" / f"{run_name}.json"


def _load_manifest(store: StageStore, run_name: str | None) -> dict:
    if not run_name:
        return {}
    p = _manifest_path(store, run_name)
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def _save_manifest(store: StageStore, run_name: str | None, planned: Sequence[PlannedStage]) -> None:
    if not run_name:
        return
    p = _manifest_path(store, run_name)
    p.parent.mkdir(parents=True, exist_ok=True)
    old = _load_manifest(store, run_name)
    old.update({ps.stage.name: {"key": ps.key.digest, "params": ps.key.params, "inputs": list(ps.key.inputs)}
                for ps in planned})
    tmp = p.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(old, indent=2, sort_keys=True), encoding="utf-8")
    os.replace(tmp, p)


def _why(stage: Stage, key: StageKey, previous: Mapping[str, Any] | None, keys: Mapping[str, StageKey],
         upstream_recomputed: set[str]) -> str:
    if previous is None:
        return "never computed"
    changed = []
    old_params = previous.get("params", {})
    new_params = key.params
    for k in sorted(set(old_params) | set(new_params)):
        if old_params.get(k) != new_params.get(k):
            changed.append(f"{k}: {old_params.get(k)!r} -> {new_params.get(k)!r}")
    if changed:
        return "parameters changed (" + ", ".join(changed) + ")"
    ups = [d for d in stage.depends if d in upstream_recomputed]
    if ups:
        return "input stage " + ", ".join(repr(u) for u in ups) + " will be recomputed"
    if previous.get("inputs") != list(key.inputs):
        return "an input changed"
    if previous.get("key") == key.digest:
        return "entry missing or removed from the store"
    return "stage version changed"


def plan_stages(stages: Sequence[Stage], store: StageStore, *, force: Sequence[str] = (),
                run_name: str | None = None) -> list[PlannedStage]:
    """Compute every stage's key and whether it must run, with the reason.

    ``force`` names stages to recompute together with everything downstream of them.
    """
    ordered = _order(stages)
    unknown = set(force) - {s.name for s in ordered}
    if unknown:
        raise UserError(f"--force: unknown stage {sorted(unknown)[0]!r}; stages are "
                        f"{', '.join(s.name for s in ordered)}")
    forced = _downstream(ordered, set(force))
    manifest = _load_manifest(store, run_name)
    keys: dict[str, StageKey] = {}
    recompute: set[str] = set()
    planned = []
    for s in ordered:
        key = store.key(s.name, s.version, dict(s.params), [keys[d] for d in s.depends] + list(s.extra_inputs),
                        schema=s.schema)
        keys[s.name] = key
        if s.name in forced:
            cached, reason = False, "forced" if s.name in force else "downstream of a forced stage"
        elif store.contains(key):
            cached, reason = True, "cached"
        else:
            cached = False
            reason = _why(s, key, manifest.get(s.name), keys, recompute)
        if not cached:
            recompute.add(s.name)
        planned.append(PlannedStage(s, key, cached, reason))
    return planned


def run_stages(stages: Sequence[Stage], store: StageStore, *, force: Sequence[str] = (),
               run_name: str | None = None, progress: Callable[[str], None] | None = None,
               heal: bool = True) -> list[StageResult]:
    """Plan, then compute the stages that need it, in dependency order.

    A cached entry that turns out to be corrupt or to violate its schema is quarantined,
    reported in one warning line and recomputed (``heal``); with ``heal=False`` it stops the
    run (a :class:`StageFailed` naming the file). When a stage fails, :class:`StageFailed` is
    raised; every stage before it stays in the store.
    """
    planned = plan_stages(stages, store, force=force, run_name=run_name)
    records: dict[str, Record] = {}
    results: list[StageResult] = []
    for ps in planned:
        s = ps.stage
        t0 = time.perf_counter()
        if progress:
            progress(f"{s.name}: {'cached' if ps.cached else 'computing'} ({ps.reason})")
        try:
            rec = None if not ps.cached else store.get(ps.key, recompute_bad=heal)
            cached = rec is not None
            if rec is None:
                rec = s.compute({d: records[d] for d in s.depends})
                if not isinstance(rec, Record):
                    raise TypeError(f"stage {s.name!r} returned {type(rec).__name__}, not a Record")
                store.put(ps.key, rec)
        except StoreError as exc:
            results.append(StageResult(s.name, False, time.perf_counter() - t0, ps.key.digest, reason=ps.reason,
                                       error=str(exc)))
            _save_manifest(store, run_name, [p for p in planned if p.stage.name in {r.name for r in results[:-1]}])
            raise StageFailed(s.name, exc, results) from exc
        except Exception as exc:  # noqa: BLE001 - reported with the stage's name, earlier results kept
            results.append(StageResult(s.name, False, time.perf_counter() - t0, ps.key.digest, reason=ps.reason,
                                       error=f"{type(exc).__name__}: {exc}"))
            _save_manifest(store, run_name, [p for p in planned if p.stage.name in {r.name for r in results[:-1]}])
            raise StageFailed(s.name, exc, results) from exc
        records[s.name] = rec
        results.append(StageResult(s.name, cached, time.perf_counter() - t0, ps.key.digest,
                                   str(store.path_for(ps.key)), ps.reason))
    _save_manifest(store, run_name, planned)
    return results
