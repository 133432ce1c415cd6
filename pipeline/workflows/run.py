"""``iristac run CONFIG.yaml``: the five stages from one config file, each through the stage store.

:func:`run_pipeline` reads and checks the config (:func:`load_pipeline_config`), builds the
stage graph from the stage registry (:func:`pipeline.stages.config.build_stages`: each stage
module's node, with the key every other entry point computes for the same work) and hands
it to :func:`pipeline.stages.graph.run_stages`: a stage is computed only when the store has
no entry for its key, so a rerun of the same config reads everything back, and a changed
parameter recomputes that stage and what depends on it. A corrupt or schema-violating entry
is quarantined, reported in one warning line and recomputed (``heal=False``, ``--no-heal``:
it stops the run). The run manifest (``<cache>/runs/<name>.json``)
lets ``--dry-run`` say why a stage would run. When the config names ``out``, the normals and
depth are also copied there with PNG/PLY pictures, and the run's summary (per stage ``name``,
``cached``, ``seconds``, ``key``, and errors against the capture's truth when it has one) is
written to ``out/run.json``.

Examples
--------
>>> import tempfile, os
>>> d = tempfile.mkdtemp()
>>> cfg = os.path.join(d, "run.yaml")
>>> _ = open(cfg, "w").write('''
... cache: cache
... synthesize: {model: bare_ring, height: 12, width: 16, mm_per_px: 0.5}
... capture: {render: true, contacts: 1, size_mm: 2.0}
... normals: {solver: nearfield}
... depth: {}
... ''')
>>> first = run_pipeline(cfg, progress=False)
>>> [(s["name"], s["cached"]) for s in first.stages]
[('synthesize', False), ('capture', False), ('normals', False), ('depth', False)]
>>> [s["cached"] for s in run_pipeline(cfg, progress=False).stages]
[True, True, True, True]
>>> [(p["name"], p["reason"]) for p in plan_pipeline(cfg, force=["normals"])][1:]
[('capture', 'cached'), ('normals', 'forced'), ('depth', 'downstream of a forced stage')]
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from pipeline.base.errors import UserError

__all__ = ["RunReport", "load_pipeline_config", "plan_pipeline", "run_pipeline"]


@dataclass
class RunReport:
    """What :func:`run_pipeline` did.

    Attributes
    ----------
    stages : list of dict
        Per stage: ``name``, ``cached``, ``seconds``, ``key`` (and ``reason``, ``path``,
        ``error`` for a failed stage).
    seconds : float
        Wall time of the whole run.
    summary : dict
        ``valid_fraction`` and, when the capture has truth, ``normal_mean_error_deg`` and
        ``depth_rmse_mm``.
    outputs : list of str
        Files written to the config's ``out`` folder.
    cache : str
        The stage store folder.
    """

    stages: list[dict]
    seconds: float
    summary: dict[str, Any] = field(default_factory=dict)
    outputs: list[str] = field(default_factory=list)
    cache: str = ""

    def to_json(self) -> dict:
        """The stable ``--json`` keys: ``stages``, ``seconds``, ``summary``, ``outputs``, ``cache``."""
        return {"stages": self.stages, "seconds": round(self.seconds, 4), "summary": self.summary,
                "outputs": self.outputs, "cache": self.cache}


def load_pipeline_config(path: str | Path) -> dict[str, Any]:
    """Read a pipeline YAML, check it against the schema, fill defaults, resolve paths.

    Relative paths (``cache``, ``out``, capture files) are relative to the config file.

    Raises
    ------
    UserError
        Missing or unreadable file, invalid YAML, unknown keys (named, with the allowed
        ones), or stage sections that contradict each other.
    """
    from data_schemas import SchemaError, read_yaml_file
    from pipeline.stages.config import resolve_config

    p = Path(path)
    if not p.is_file():
        raise UserError(f"{p}: no such config file")
    try:
        obj = read_yaml_file(p)
    except SchemaError as exc:
        raise UserError(str(exc)) from None
    if obj is None:
        obj = {}
    if not isinstance(obj, dict):
        raise UserError(f"{p}: expected a mapping of stage sections at the top level, got {type(obj).__name__}")
    return resolve_config(obj, p.resolve().parent, str(p))


def _run_name(config_path: Path) -> str:
    """Manifest name of a config: its stem plus a hash of its absolute path."""
    full = str(config_path.resolve())
    return f"{config_path.stem}-{hashlib.sha256(full.encode()).hexdigest()[:10]}"


def _store(config: dict, cache):
    from pipeline.base.store import StageStore

    return StageStore(cache if cache is not None else config.get("cache"))


def plan_pipeline(config_path: str | Path, *, cache: str | Path | None = None,
                  force: Sequence[str] = ()) -> list[dict]:
    """What :func:`run_pipeline` would recompute and why (``--dry-run``); computes nothing.

    Returns
    -------
    list of dict
        Per stage in run order: ``name``, ``cached`` (the store has its entry), ``key`` and
        ``reason`` (``cached``, ``never computed``, ``parameters changed (...)``, ``input
        stage 'x' will be recomputed``, ``forced`` ...).
    """
    from pipeline.stages.config import build_stages
    from pipeline.stages.graph import plan_stages

    config = load_pipeline_config(config_path)
    store = _store(config, cache)
    planned = plan_stages(build_stages(config), store, force=force, run_name=_run_name(Path(config_path)))
    return [{"name": ps.stage.name, "cached": ps.cached, "key": ps.key.digest, "reason": ps.reason}
            for ps in planned]


def run_pipeline(config_path: str | Path, *, cache: str | Path | None = None, out: str | Path | None = None,
                 force: Sequence[str] = (), device: str | None = None, progress: bool = True,
                 heal: bool = True) -> RunReport:
    """Run the stages of a pipeline config through the stage store.

    Parameters
    ----------
    config_path : path
        The pipeline YAML (schema ``data_schemas/configs/pipeline.json``).
    cache : path, optional
        Stage store folder; overrides the config's ``cache``.
    out : path, optional
        Output folder; overrides the config's ``out``.
    force : sequence of str
        Stages to recompute together with everything downstream of them.
    device : str, optional
        Torch device; overrides the config's ``device``.
    progress : bool
        One line per stage on stderr and progress bars in long stages.
    heal : bool
        A corrupt or schema-violating store entry is quarantined (moved aside, never deleted),
        reported in one warning line and recomputed; False stops the run on it instead.

    Returns
    -------
    RunReport

    Raises
    ------
    pipeline.stages.graph.StageFailed
        A stage failed (its message names the stage and the bad input); the stages before
        it are in the store and ``exc.results`` says what ran.
    UserError
        The config is invalid.
    """
    from pipeline.stages.config import build_stages
    from pipeline.stages.graph import run_stages

    t0 = time.perf_counter()
    config = load_pipeline_config(config_path)
    if out is not None:
        config["out"] = str(Path(out).resolve())
    store = _store(config, cache)
    stages = build_stages(config, device=device, progress=progress)
    if progress:
        for s in stages:
            if s.name != "capture":  # the capture plan draws its own bar, step by step
                s.compute = _ticking(s.name, s.compute)
    say = (lambda msg: print(f"iristac run: {msg}", file=sys.stderr, flush=True)) if progress else None
    results = run_stages(stages, store, force=force, run_name=_run_name(Path(config_path)), progress=say,
                         heal=heal)
    report = RunReport(stages=[r.to_json() for r in results], seconds=0.0, cache=str(store.root))
    keys = {r.name: r for r in results}
    if "normals" in keys:
        report.summary, report.outputs = _finish(config, keys)
    report.seconds = time.perf_counter() - t0
    if config.get("out"):
        out = Path(config["out"]) / "run.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report.to_json(), indent=2, sort_keys=True), encoding="utf-8")
        report.outputs.append(str(out))
    return report


def _ticking(name: str, compute):
    """``compute`` with an elapsed-time bar on stderr while it runs (stages without steps to count)."""
    import threading

    def run(inputs):
        from tqdm import tqdm

        bar = tqdm(desc=f"{name}", bar_format="{desc}: {elapsed} elapsed", leave=False, file=sys.stderr)
        stop = threading.Event()

        def tick():
            while not stop.wait(0.5):
                bar.refresh()

        t = threading.Thread(target=tick, daemon=True)
        t.start()
        try:
            return compute(inputs)
        finally:
            stop.set()
            t.join()
            bar.close()

    return run


def _finish(config: dict, results) -> tuple[dict, list[str]]:
    """Errors against the capture's truth, and the copies/pictures in ``out``."""
    import numpy as np

    from pipeline.base.store import read_record
    from pipeline.results.evaluate import truth_errors
    from pipeline.results.exports import link_results, write_pictures
    from pipeline.stages import stage_module

    def rec(name):
        return read_record(results[name].path, schema=stage_module(name).SPEC.schema) if name in results else None

    n_rec, d_rec, cap = rec("normals"), rec("depth"), rec("capture")
    summary: dict[str, Any] = {"valid_fraction": float(np.asarray(n_rec.data["mask"]).mean())}
    if d_rec is not None:
        summary.update(truth_errors(cap, n_rec, d_rec))
    outputs: list[str] = []
    if config.get("out") and d_rec is not None:
        out = Path(config["out"])
        files = link_results(out, {"normals": results["normals"].path, "depth": results["depth"].path})
        if config.get("images", True):
            files += write_pictures(out, n_rec, d_rec, float(n_rec.meta["mm_per_px"]))
        outputs = [str(f) for f in files]
    return summary, outputs
