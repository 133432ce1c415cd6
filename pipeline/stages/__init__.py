"""The stage registry: one module per stage, every entry point goes through it.

=============  =============================================  ===============================
stage          module                                         writes (schema)
=============  =============================================  ===============================
synthesize     :mod:`pipeline.stages.synthesize`              ``illumination``
calibrate      :mod:`pipeline.stages.calibrate`               ``calibration``
capture        :mod:`pipeline.stages.capture`                 ``capture``
normals        :mod:`pipeline.stages.normals`                 ``normals``
depth          :mod:`pipeline.stages.depth`                   ``depth``
=============  =============================================  ===============================

Each stage module owns, in one place:

- ``SPEC``: its name, version, output schema and run-config defaults
  (:class:`pipeline.stages.base.StageSpec`);
- ``params(section)``: the parameters that change its result, which with the identities of its
  inputs (:func:`pipeline.base.identity.record_key`) make its store key;
- ``resolve(section, config, base, source)``: check and fill its run-config section;
- ``compute(...)``: the computation, a :class:`~pipeline.base.store.Record` out;
- ``run(store, ...)``: key, look up, compute if missing (or bad: the cache heals), for the
  entry points that call one stage (``reconstruct``, ``batch``, ``demo``, ``compare-modes``);
- ``node(config, ctx)``: its node of the graph ``iristac run`` builds from a config
  (:mod:`pipeline.stages.config`, run by :mod:`pipeline.stages.graph`).

That contract is :class:`pipeline.stages.base.StageModule` (a ``typing.Protocol``, checked for
every stage by a test). So the same work reached through ``run``, ``reconstruct``, ``batch``,
``demo`` or ``compare-modes`` has one key and is one cache entry. A new stage: the recipe in
``docs/developing.md`` lists every file.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, cast

if TYPE_CHECKING:
    from pipeline.stages.base import StageModule

__all__ = ["STAGE_ORDER", "stage_module"]

#: The stages, in the order ``iristac run`` runs them.
STAGE_ORDER = ("synthesize", "calibrate", "capture", "normals", "depth")


def stage_module(name: str) -> StageModule:
    """The module of stage ``name`` (imported on first use).

    Examples
    --------
    >>> stage_module("depth").SPEC.schema
    'depth'
    """
    if name not in STAGE_ORDER:
        raise ValueError(f"unknown stage {name!r}; stages are {', '.join(STAGE_ORDER)}")
    return cast("StageModule", importlib.import_module(f"pipeline.stages.{name}"))
