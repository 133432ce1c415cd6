"""The recipes in ``docs/developing.md`` ("Where a new part goes") are true to the code.

Each recipe must name the files a new part of its kind touches; here every file a recipe
names exists, the files this test knows a part must reach are in its recipe, and every part
registered today is in each of those places (a recipe that misses a place would fail for the
parts that are there already).
"""

from __future__ import annotations

import ast
import json
import re

import pytest

from helpers import REPO

DOC = REPO / "docs" / "developing.md"

#: Per recipe heading: the files every part of that kind reaches (checked below, part by part).
RECIPES = {
    "A solver": ["pipeline/normals/solve.py", "pipeline/solving/model_solvers.py", "pipeline/base/registry.py",
                 "pipeline/solving/frame_solvers.py", "tests/pipeline/normals/test_fast_paths.py",
                 "docs/reconstruction.md"],
    "An integrator": ["pipeline/depth/__init__.py", "pipeline/base/registry.py", "docs/reconstruction.md",
                      "tests/pipeline/depth/test_depth_integrators.py"],
    "A lighting mode": ["data_schemas/configs/mode.json", "docs/renderer.md"],
    "A lens surface": ["sim/optics/surfaces.py", "sim/optics/lens.py", "sim/scene.py",
                       "data_schemas/configs/scene.json", "sim/optics/kernel.py", "sim/optics/engine.py",
                       "tests/sim/test_intersect_cases.py"],
    "A stage": ["pipeline/stages/__init__.py", "data_schemas/configs/pipeline.json",
                "tests/pipeline/stages/test_keys.py", "tests/pipeline/stages/test_contract.py", "pipeline/workflows/run.py",
                "docs/running.md"],
}


def _recipe(heading: str) -> str:
    text = DOC.read_text(encoding="utf-8")
    m = re.search(rf"^### {re.escape(heading)}\b.*?(?=^##)", text, flags=re.S | re.M)
    assert m, f"docs/developing.md has no recipe '### {heading}'"
    return m.group(0)


def _paths(section: str) -> set[str]:
    """Repository paths named in backticks (``dir/file.ext``, ``dir/<name>.py``, ``path: detail``)."""
    out = set()
    for token in re.findall(r"`([^`]+)`", section):
        token = token.split(":")[0].strip()
        if "/" in token and " " not in token and re.search(r"\.(py|json|yaml|md)$|/$", token):
            out.add(token)
    return out


def _read(rel: str) -> str:
    return (REPO / rel).read_text(encoding="utf-8")


def _table_names(doc: str, first: str) -> set[str]:
    """The backticked names in the first cells of the markdown table whose rows include ``first``."""
    names: set[str] = set()
    for block in re.split(r"\n\s*\n", _read(doc)):
        rows = [r for r in block.splitlines() if r.startswith("|")]
        cells = [r.split("|")[1] for r in rows]
        if any(f"`{first}`" in c for c in cells):
            names |= {n for c in cells for n in re.findall(r"`([^`]+)`", c)}
    return names


@pytest.mark.parametrize("heading", RECIPES)
def test_each_recipe_names_files_that_exist_and_every_place_a_part_reaches(heading):
    named = _paths(_recipe(heading))
    missing = [p for p in RECIPES[heading] if p not in named]
    assert not missing, f"recipe '{heading}' does not name {missing}"
    for p in named:
        if "<" in p:  # a file the new part adds: its folder exists
            p = p[:p.index("<")].rsplit("/", 1)[0] + "/"
        assert (REPO / p).exists(), f"recipe '{heading}' names {p}, which does not exist"


def test_every_solver_is_where_the_solver_recipe_says():
    from pipeline.base.registry import SOLVERS

    fast_tests = _read("tests/pipeline/normals/test_fast_paths.py")
    documented = _table_names("docs/reconstruction.md", "lstsq")
    for e in SOLVERS:
        module, _, attr = e.target.partition(":")
        assert module in ("pipeline.normals.solve", "pipeline.solving.model_solvers") and attr == f"stack_{e.name.replace('-', '_')}", e
        assert e.name in documented, f"docs/reconstruction.md's solvers table has no row for {e.name}"
        assert {"needs", "patterns"} <= set(e.info), f"{e.name}: the registry entry lacks its facts"
        if e.info.get("fast"):
            assert e.info["fast"] == f"pipeline.solving.frame_solvers:fast_{e.name}", e.info["fast"]
            assert re.search(rf"\b{e.name}\b", fast_tests), \
                f"tests/pipeline/normals/test_fast_paths.py does not test {e.name}'s fast path"


def test_every_integrator_is_where_the_integrator_recipe_says():
    from pipeline.base.registry import INTEGRATORS

    tree = ast.parse(_read("pipeline/depth/__init__.py"))
    where = next(ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
                 and any(isinstance(t, ast.Name) and t.id == "_WHERE" for t in n.targets))
    documented = _table_names("docs/reconstruction.md", "dct")
    for e in INTEGRATORS:
        module, _, attr = e.target.partition(":")
        assert module.startswith("pipeline.depth.") and where.get(attr) == module.rsplit(".", 1)[1], e
        assert e.name in documented, f"docs/reconstruction.md's integrators table has no row for {e.name}"
    assert "INTEGRATORS.names()" in _read("tests/pipeline/depth/test_depth_integrators.py")


def test_every_lighting_mode_is_where_the_mode_recipe_says():
    from pipeline.base.modes import load_mode
    from pipeline.base.registry import list_modes
    from pipeline.workflows.demo import builtin_modes

    documented = _table_names("docs/renderer.md", "point")
    for name in list_modes():
        assert load_mode(name).name and name in documented, f"docs/renderer.md's modes table has no row for {name}"
    assert set(builtin_modes()) == set(list_modes())


def test_every_lens_surface_is_where_the_surface_recipe_says():
    from sim.optics.surfaces import SURFACES

    lens = _read("sim/optics/lens.py")
    for kind in SURFACES.values():
        module, _, cls = kind.target.partition(":")
        assert (REPO / (module.replace(".", "/") + ".py")).is_file(), kind
        assert f"class {cls}(ConvexSet)" in (REPO / (module.replace(".", "/") + ".py")).read_text(), kind
        assert cls in lens, f"sim/optics/lens.py (LensBody) never builds {cls}"
        assert kind.part in ("side", "top", "bottom") and set(kind.engines) <= {"kernel", "torch"}


def test_every_stage_is_where_the_stage_recipe_says():
    from pipeline.stages import STAGE_ORDER, stage_module

    sections = json.loads(_read("data_schemas/configs/pipeline.json"))["properties"]
    running, keys = _read("docs/running.md"), _read("tests/pipeline/stages/test_keys.py")
    for name in STAGE_ORDER:
        schema = stage_module(name).SPEC.schema
        assert (REPO / "data_schemas" / "stages" / f"{schema}.json").is_file(), name
        assert name in sections, f"data_schemas/configs/pipeline.json has no {name!r} section"
        assert f'"{name}":' in keys, f"tests/pipeline/stages/test_keys.py has no KEY_CASES for {name}"
        assert name in running, f"docs/running.md never mentions the {name} section"
