"""Every stage module keeps the stage contract (:class:`pipeline.stages.base.StageModule`): the
same ``params``, ``resolve`` and ``node`` signatures, and a ``compute`` and a ``run`` that
starts with the store."""

from __future__ import annotations

import inspect

import pytest

from pipeline.stages import STAGE_ORDER, stage_module
from pipeline.stages.base import StageModule, StageSpec


def _names(func) -> list[str]:
    return [p.name for p in inspect.signature(func).parameters.values()
            if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]


@pytest.mark.parametrize("name", STAGE_ORDER)
def test_every_stage_keeps_the_contract(name):
    s = stage_module(name)
    assert isinstance(s, StageModule), f"stage {name} lacks part of the contract"
    assert isinstance(s.SPEC, StageSpec) and s.SPEC.name == name
    assert len(_names(s.params)) == 1, f"{name}.params must take one section: {inspect.signature(s.params)}"
    assert len(_names(s.resolve)) == 4, f"{name}.resolve(section, config, base, source): {inspect.signature(s.resolve)}"
    assert _names(s.node)[:2] == ["config", "ctx"]
    assert _names(s.run)[0] == "store" and callable(s.compute)
    for part in ("params", "resolve", "compute", "run", "node"):
        assert part in s.__all__, f"{name}.{part} is not in its __all__"


def test_a_module_without_run_is_not_a_stage():
    import types

    fake = types.SimpleNamespace(SPEC=StageSpec("x", 1, "x"), params=lambda s: {}, resolve=lambda *a: None,
                                 compute=lambda: None, node=lambda c, x: None)
    assert not isinstance(fake, StageModule)
