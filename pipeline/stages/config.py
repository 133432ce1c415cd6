"""A run config (``iristac run CONFIG.yaml``) -> the graph of the stages it names.

:func:`resolve_config` validates the config (the solver, integrator and object choices come
from their registries), fills every default from the stage modules' :class:`StageSpec` and
makes relative paths absolute, so a stage's parameters are exactly what changes its result
(writing a default out explicitly, or moving the config file, does not recompute anything).
:func:`build_stages` asks each stage module present in the config for its graph node
(``node(...)``): the same key and the same computation the other entry points get from that
module.

Stages whose section is absent are skipped; a stage that needs an absent one says so.

Examples
--------
>>> cfg = resolve_config({"synthesize": {"model": "bare_ring", "height": 8, "width": 10},
...                       "capture": {"render": True, "contacts": 1}, "normals": {}, "depth": {}})
>>> [s.name for s in build_stages(cfg)]
['synthesize', 'capture', 'normals', 'depth']
>>> cfg["normals"]["lights"], cfg["capture"]["mode"]
('illumination', 'monochromatic')
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any, Mapping

from pipeline.base.errors import UserError
from pipeline.stages import STAGE_ORDER, stage_module
from pipeline.stages.base import config_path

__all__ = ["resolve_config", "build_stages", "config_choices"]


def config_choices() -> dict[str, tuple[str, ...]]:
    """The registries behind the ``x-choices`` of ``data_schemas/configs/pipeline.json``."""
    from pipeline.base.registry import INTEGRATORS, SOLVERS
    from sim.contacts import OBJECTS

    return {"solvers": SOLVERS.names(), "integrators": INTEGRATORS.names(), "objects": OBJECTS}


def resolve_config(config: Mapping[str, Any], base_dir: str | os.PathLike = ".", source: str = "<config>"
                   ) -> dict[str, Any]:
    """Validate a parsed pipeline config, fill defaults and make paths absolute.

    Parameters
    ----------
    config : mapping
        The parsed YAML (schema ``data_schemas/configs/pipeline.json``).
    base_dir : path-like
        Relative paths in the config are relative to this folder (the config file's).
    source : str
        Named in error messages (the config file).

    Returns
    -------
    dict
        A new config with every stage section's defaults filled in.

    Raises
    ------
    UserError
        Unknown keys (naming the key and the allowed ones), wrong types, or stage sections
        that contradict each other (e.g. ``capture`` with both ``file`` and ``render``).
    """
    from data_schemas import SchemaError, validate_config

    try:
        validate_config("pipeline", dict(config), source, choices=config_choices())
    except SchemaError as exc:
        raise UserError(str(exc)) from None
    base = Path(base_dir).resolve()
    cfg = copy.deepcopy(dict(config))
    for name in STAGE_ORDER:
        if name in cfg:
            cfg[name] = {**stage_module(name).SPEC.defaults, **(cfg[name] or {})}
    for key in ("cache", "out"):
        if key in cfg:
            cfg[key] = config_path(cfg[key], base)
    for name in STAGE_ORDER:  # each stage checks and fills its own section
        if name in cfg:
            stage_module(name).resolve(cfg[name], cfg, base, source)
    return cfg


def build_stages(config: Mapping[str, Any], *, device: str | None = None, progress: bool = False) -> list:
    """The graph nodes of a resolved config (:func:`resolve_config`), in run order.

    Parameters
    ----------
    config : mapping
        A config returned by :func:`resolve_config`.
    device : str, optional
        Torch device (default: the config's ``device``, else ``cpu``). Not part of any key.
    progress : bool
        Progress bars inside long stages (capture).

    Returns
    -------
    list of pipeline.stages.graph.Stage

    Raises
    ------
    UserError
        A stage needs one that is not configured (e.g. ``capture.render`` without
        ``synthesize``, ``normals.lights: calibration`` without ``calibrate``).
    """
    from pipeline.stages.base import NodeContext

    ctx = NodeContext(device or config.get("device") or "cpu", progress, frozenset(set(config) & set(STAGE_ORDER)))
    return [stage_module(name).node(config, ctx) for name in STAGE_ORDER if name in config]
