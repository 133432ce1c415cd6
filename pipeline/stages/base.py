"""What every stage module shares: the contract it keeps (:class:`StageModule`) and its
:class:`StageSpec`.

A stage's output key hashes (stage name, stage version, canonical parameters, input keys)
(:meth:`pipeline.base.store.StageStore.key`). Each stage module owns the first three
(:class:`StageSpec` and its ``params(...)``); the input keys are the *identities* of the
records the stage reads (:func:`pipeline.base.identity.record_key`).

A standalone capture file is special: the capture stage reads files too (``capture: {file:
...}`` in a run config), so its identity is that stage's key over the file
(:func:`pipeline.stages.capture.capture_key`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol, Sequence, runtime_checkable

from pipeline.base.errors import UserError
from pipeline.base.store import Record, StageKey, StageStore

__all__ = ["StageModule", "StageSpec", "NodeContext", "config_path"]


@dataclass(frozen=True)
class StageSpec:
    """Name, version, output schema and config defaults of one stage.

    Attributes
    ----------
    name : str
        The stage name (the store folder, ``--force NAME``, the run config's section).
    version : int
        Bump when the stage's computation changes its result: old entries stop matching.
    schema : str
        The schema of the records it writes (``data_schemas/stages/<schema>.json``).
    defaults : mapping
        Defaults of its run-config section.
    """

    name: str
    version: int
    schema: str
    defaults: Mapping[str, Any] = field(default_factory=dict)

    def key(self, store: StageStore, params: Mapping[str, Any], inputs: Sequence[str | StageKey] = ()) -> StageKey:
        """The store key of this stage's result for ``params`` computed from ``inputs``."""
        return store.key(self.name, self.version, params, inputs, schema=self.schema)

    def get_or_compute(self, store: StageStore, params: Mapping[str, Any], inputs: Sequence[str | StageKey],
                       compute: Callable[[], Record], *, force: bool = False,
                       heal: bool = True) -> tuple[Record, StageKey, bool]:
        """``(record, key, cached)``: the stored result, or ``compute()`` stored and returned.

        With ``heal`` a corrupt or schema-violating entry is quarantined (kept, never deleted),
        reported in one warning line and recomputed; without it, it is a
        :class:`~pipeline.base.store.StoreError`.
        """
        key = self.key(store, params, inputs)
        rec, cached = store.get_or_compute(key, compute, recompute_bad=heal, force=force)
        return rec, key, cached


@runtime_checkable
class StageModule(Protocol):
    """The contract of a stage module (``pipeline/stages/<name>.py``), one signature each where
    the stages agree (``tests/pipeline/stages/test_graph.py`` checks every stage against it).

    ``compute`` and ``run`` take what the stage reads (a capture, a normals record, ...), so
    their arguments differ from stage to stage; ``run`` starts with the store and returns
    ``(record, key, cached)``.
    """

    SPEC: StageSpec

    def params(self, section: Mapping[str, Any]) -> dict:
        """The key parameters of a (default-filled) section."""

    def resolve(self, section: dict, config: Mapping[str, Any], base: Path, source: str) -> None:
        """Check and fill a run config's section in place (paths absolute, defaults that depend
        on the rest of ``config``)."""

    def compute(self, *args: Any, **kwargs: Any) -> Any:
        """The result record, without the store."""

    def run(self, store: StageStore, *args: Any, **kwargs: Any) -> Any:
        """``(record, key, cached)`` through the store."""

    def node(self, config: Mapping[str, Any], ctx: NodeContext) -> Any:
        """Its node of the graph ``iristac run`` builds."""


@dataclass(frozen=True)
class NodeContext:
    """What a stage module's ``node(config, ctx)`` needs besides the config: the torch device,
    whether to draw progress bars, and the stage sections present (for :meth:`need`)."""

    device: str = "cpu"
    progress: bool = False
    present: frozenset = frozenset()

    def need(self, stage: str, other: str, why: str = "") -> None:
        """UserError unless the config has the section ``other`` that ``stage`` reads."""
        if other not in self.present:
            what = f"stage {stage!r} {why}".rstrip()
            raise UserError(f"config: {what} needs the {other!r} section, which is absent")


def config_path(path: str, base: Path) -> str:
    """A path from a run config, absolute (relative paths are relative to the config's folder)."""
    p = Path(os.path.expanduser(path))
    return str(p if p.is_absolute() else (base / p).resolve())
