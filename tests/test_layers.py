"""The layers point down: read every import of the four packages (function-level ones too) and
fail on an import that reaches up a layer, on an import cycle, on a third-party import in
the base layer that is not one of its few libraries, or on an import of another module's
private name (``_name``; a package's private modules, ``pkg._mod``, only inside ``pkg``).
The registries' string targets (``"module:attribute"``, imported only when used) are resolved
too: each names a module of the packages, below the entry points, that defines the attribute.

The layers, lowest first (``docs/developing.md`` draws them). A module may import modules of
its own layer or of a lower one; a module nobody placed is an error, so a new module is put
in its layer on purpose.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

from helpers import REPO

PACKAGES = ("sim", "calibration", "pipeline", "data_schemas")

#: (layer, module prefixes), lowest first. ``pipeline`` alone is ``pipeline/__init__.py``
#: (the version string), which the base layer's store reads.
LAYERS = [
    ("schemas", ["data_schemas"]),
    ("base", ["pipeline.base", "pipeline"]),
    ("physics and numerics", ["sim", "pipeline.normals", "pipeline.depth", "pipeline.frame_pipeline",
                              "pipeline.results", "pipeline.charts"]),
    ("calibration and capture", ["calibration", "pipeline.capture", "pipeline.solving"]),
    ("stage registry", ["pipeline.stages"]),
    ("entry points", ["pipeline.streaming", "pipeline.workflows", "pipeline.live"]),
    ("command line and benchmarks", ["pipeline.cli", "pipeline.bench", "pipeline.__main__"]),
]

#: Packages of one layer that import nothing of each other, in either direction: the normals
#: solvers and the depth integrators. What does both (normals, then heights, of many frames)
#: is a frame pipeline (``pipeline.frame_pipeline``); what both need sits below them
#: (``pipeline.base.pixel_mask``).
APART = [("pipeline.normals", "pipeline.depth")]

#: Third-party libraries the base layer may import (besides the standard library).
BASE_LIBRARIES = {"numpy", "torch", "h5py", "hdf5plugin", "zstandard", "yaml", "jsonschema", "threadpoolctl"}


def module_files(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file of the packages under ``root``."""
    out = {}
    for pkg in PACKAGES:
        for p in sorted((root / pkg).rglob("*.py")):
            parts = list(p.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int, str]]:
    """``(imported name, line, statement)`` of every import in the file, at any depth; an
    imported name is resolved to the deepest module of the packages it names (or left as
    the top-level library name)."""
    text = path.read_text(encoding="utf-8")
    tree = ast.parse(text, str(path))
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    # The statement's own lines, for the message: split once per file, as ast.get_source_segment
    # splits the whole text on every call (8 of this test's 9 s once).
    lines = text.splitlines()
    found: dict[tuple[str, int], str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        else:
            continue
        for t in targets:
            parts = t.split(".")
            while len(parts) > 1 and ".".join(parts) not in modules:
                parts = parts[:-1]
            found[(".".join(parts), node.lineno)] = " ".join(
                line.strip() for line in lines[node.lineno - 1:(node.end_lineno or node.lineno)])
    return [(t, line, stmt) for (t, line), stmt in found.items()]


def layer_of(module: str) -> int | None:
    best, rank = -1, None
    for i, (_, prefixes) in enumerate(LAYERS):
        for pre in prefixes:
            if (module == pre or module.startswith(pre + ".")) and len(pre) > best and \
                    (pre != "pipeline" or module == "pipeline"):
                best, rank = len(pre), i
    return rank


def check(root: Path) -> list[str]:
    """Every violation under ``root``, one line each (empty: the layers hold)."""
    modules = module_files(root)
    problems: list[str] = []
    graph: dict[str, set[str]] = {m: set() for m in modules}
    where: dict[tuple[str, str], str] = {}
    for name, path in modules.items():
        rank = layer_of(name)
        rel = path.relative_to(root)
        if rank is None:
            problems.append(f"{rel}: module {name} is in no layer (add it to LAYERS in tests/test_layers.py)")
            continue
        for target, line, stmt in imports_of(name, path, modules):
            if target in modules:
                if target != name:
                    graph[name].add(target)
                    where[(name, target)] = f"{rel}:{line}"
                t_rank = layer_of(target)
                if t_rank is not None and t_rank > rank:
                    problems.append(f"{rel}:{line}: {name} ({LAYERS[rank][0]}) imports {target} "
                                    f"({LAYERS[t_rank][0]}), a layer above it: {stmt.strip()}")
            elif LAYERS[rank][0] == "base":
                top = target.split(".")[0]
                if top not in sys.stdlib_module_names and top not in BASE_LIBRARIES and top not in PACKAGES:
                    problems.append(f"{rel}:{line}: the base layer imports {top}, not one of its libraries "
                                    f"({', '.join(sorted(BASE_LIBRARIES))})")
    problems += private_imports(root, modules)
    for cycle in _cycles(graph):
        steps = " -> ".join(f"{a} ({where[(a, b)]})" for a, b in zip(cycle, cycle[1:] + cycle[:1]))
        problems.append(f"import cycle: {steps} -> {cycle[0]}")
    return problems


def _inside(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def apart_imports(root: Path, pairs=APART) -> list[str]:
    """Every import (function-level ones too) of a module of one package of a pair in
    :data:`APART` from a module of the other, one line each."""
    modules = module_files(root)
    problems = []
    for name, path in modules.items():
        for one, other in [(a, b) for a, b in pairs] + [(b, a) for a, b in pairs]:
            if not _inside(name, one):
                continue
            for target, line, stmt in imports_of(name, path, modules):
                if _inside(target, other):
                    problems.append(f"{path.relative_to(root)}:{line}: {name} imports {target}, but {one} and "
                                    f"{other} import nothing of each other (tests/test_layers.py APART): {stmt}")
    return problems


def private_imports(root: Path, modules: dict[str, Path]) -> list[str]:
    """Every import of another module's private name, one line each."""
    problems = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        for node in ast.walk(tree):
            for owner, imported in _imported_names(node, package, modules):
                if owner.split(".")[0] not in PACKAGES:
                    continue
                if f"{owner}.{imported}" in modules:  # a module: private ones only inside their package
                    if imported.startswith("_") and name != owner and not name.startswith(owner + "."):
                        problems.append(f"{path.relative_to(root)}:{node.lineno}: {name} imports the private module "
                                        f"{owner}.{imported} from outside its package")
                elif imported.startswith("_") and not imported.startswith("__") and owner != name:
                    problems.append(f"{path.relative_to(root)}:{node.lineno}: {name} imports the private name "
                                    f"{imported} of {owner}")
    return problems


def _imported_names(node, package: list[str], modules: dict[str, Path]) -> list[tuple[str, str]]:
    """``(module, name)`` of every name an import statement takes from a module (``import a.b``:
    ``("a", "b")``)."""
    if isinstance(node, ast.Import):
        return [(".".join(a.name.split(".")[:i]), part) for a in node.names
                for i, part in enumerate(a.name.split(".")) if i > 0]
    if isinstance(node, ast.ImportFrom):
        base = node.module or ""
        if node.level:
            base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
        return [(base, a.name) for a in node.names]
    return []


def registry_targets() -> list[tuple[str, str]]:
    """``(what, "module:attribute")`` of every registered implementation and fast path."""
    from pipeline.base.registry import INTEGRATORS, SOLVERS

    out = []
    for reg in (SOLVERS, INTEGRATORS):
        for e in reg:
            out.append((f"{reg.kind} {e.name}", e.target))
            if e.info.get("fast"):
                out.append((f"{reg.kind} {e.name} (fast path)", e.info["fast"]))
    return out


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (a list of modules) per strongly connected component with more than one module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    comps: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    out = []
    for comp in comps:  # walk one cycle inside the component
        members, path, v = set(comp), [comp[0]], comp[0]
        while True:
            v = min(w for w in graph[v] if w in members)
            if v in path:
                out.append(path[path.index(v):])
                break
            path.append(v)
    return out


def test_the_layers_point_down_and_nothing_imports_in_a_circle():
    problems = check(REPO)
    assert not problems, "\n".join(problems)


def test_normals_and_depth_do_not_import_each_other():
    problems = apart_imports(REPO)
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("files, expected", [
    ({"pipeline/normals/solve.py": "def f():\n    from pipeline.depth.fast import FastDST\n",
      "pipeline/depth/fast.py": "FastDST = 1\n"},
     "pipeline.normals.solve imports pipeline.depth.fast, but pipeline.normals and pipeline.depth"),
    ({"pipeline/depth/__init__.py": "from pipeline.normals import masking\n", "pipeline/normals/masking.py": ""},
     "pipeline.depth imports pipeline.normals.masking, but pipeline.depth and pipeline.normals"),
    ({"pipeline/depth/poisson.py": "from ..normals import result\n", "pipeline/normals/result.py": ""},
     "pipeline.depth.poisson imports pipeline.normals.result"),
])
def test_the_apart_check_catches_an_import_either_way(tmp_path, files, expected):
    problems = apart_imports(_tree(tmp_path, files))
    assert any(expected in p for p in problems), problems


def test_the_apart_check_passes_a_pipeline_that_imports_both(tmp_path):
    files = {"pipeline/frame_pipeline/cpu_batch.py": "from pipeline.depth.fast import F\nfrom pipeline.normals.fast import N\n",
             "pipeline/depth/fast.py": "from pipeline.base.pixel_mask import PixelMask\n",
             "pipeline/normals/fast.py": "from pipeline.base.pixel_mask import PixelMask\n",
             "pipeline/base/pixel_mask.py": ""}
    assert apart_imports(_tree(tmp_path, files)) == []


@pytest.mark.parametrize("what, target", registry_targets())
def test_registry_targets_resolve_below_the_entry_points(what, target):
    module, _, attr = target.partition(":")
    modules = module_files(REPO)
    assert module in modules, f"{what}: {target} names no module of the packages"
    tree = ast.parse(modules[module].read_text(encoding="utf-8"))
    defined = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    defined |= {t.id for n in tree.body if isinstance(n, ast.Assign) for t in n.targets if isinstance(t, ast.Name)}
    assert attr in defined, f"{what}: {module} defines no {attr!r}"
    assert layer_of(module) <= [n for n, _ in LAYERS].index("stage registry"), \
        f"{what}: {module} is above the stage registry (an entry point or the command line)"


def test_every_layer_holds_modules():
    modules = module_files(REPO)
    used = {layer_of(m) for m in modules}
    assert used == set(range(len(LAYERS)))
    base = [m for m in modules if layer_of(m) == 1]
    assert "pipeline.base.store" in base and "pipeline.base.frames" in base and "pipeline.base.registry" in base


def _tree(root: Path, files: dict[str, str]) -> Path:
    for pkg in PACKAGES:
        (root / pkg).mkdir(parents=True, exist_ok=True)
        (root / pkg / "__init__.py").write_text("")
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        if p.parent.name != root.name and not (p.parent / "__init__.py").exists():
            (p.parent / "__init__.py").write_text("")
        p.write_text(text)
    return root


@pytest.mark.parametrize("files, expected", [
    # base reaching up into sim, even from inside a function
    ({"pipeline/base/store.py": "def f():\n    from sim.render import x\n", "sim/render.py": "x = 1\n"},
     "pipeline.base.store (base) imports sim.render (physics and numerics), a layer above it"),
    # sim reaching up to an entry point
    ({"sim/scene.py": "import pipeline.workflows.reconstruct\n", "pipeline/workflows/reconstruct.py": ""},
     "sim.scene (physics and numerics) imports pipeline.workflows.reconstruct (entry points)"),
    # two modules of one layer importing each other (the old lens <-> torus)
    ({"sim/optics/lens.py": "from sim.optics.torus import A\n",
      "sim/optics/torus.py": "def f():\n    from sim.optics.lens import B\n"},
     "import cycle: sim.optics.lens"),
    # a relative import resolves like an absolute one
    ({"pipeline/base/frames.py": "from ..stages import graph\n", "pipeline/stages/graph.py": ""},
     "pipeline.base.frames (base) imports pipeline.stages.graph (stage registry)"),
    # the base layer may not pull in a heavy library
    ({"pipeline/base/hashing.py": "import scipy.ndimage\n"}, "the base layer imports scipy"),
    # an unplaced module
    ({"pipeline/newthing.py": ""}, "module pipeline.newthing is in no layer"),
    # another module's private name, and a package's private module from outside the package
    ({"sim/a.py": "from sim.b import _x\n", "sim/b.py": "_x = 1\n"}, "sim.a imports the private name _x of sim.b"),
    ({"calibration/a.py": "from pipeline.normals import _torch\n", "pipeline/normals/_torch.py": ""},
     "calibration.a imports the private module pipeline.normals._torch from outside its package"),
])
def test_the_check_catches_what_it_is_for(tmp_path, files, expected):
    problems = check(_tree(tmp_path, files))
    assert any(expected in p for p in problems), problems


def test_a_clean_tree_passes(tmp_path):
    files = {"pipeline/base/store.py": "import numpy\nfrom pipeline.base import hashing\n",
             "pipeline/base/hashing.py": "import json\n",
             "sim/render.py": "from pipeline.base.store import x\n",
             "pipeline/stages/depth.py": "from sim import render\nfrom . import graph\n",
             "pipeline/stages/graph.py": ""}
    assert check(_tree(tmp_path, files)) == []
