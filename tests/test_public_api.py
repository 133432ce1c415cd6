"""sim and calibration say what they offer: every name in ``__all__`` resolves (to a function,
class or constant, not a submodule), and importing the package loads neither torch nor Numba."""

from __future__ import annotations

import subprocess
import sys
import types

import pytest

from helpers import REPO


@pytest.mark.parametrize("package", ["sim", "calibration"])
def test_public_names_resolve(package):
    pkg = __import__(package)
    assert pkg.__all__ and pkg.__doc__
    for name in pkg.__all__:
        assert not isinstance(getattr(pkg, name), types.ModuleType), name
        assert name in pkg.__doc__, f"{package}'s docstring does not list {name}"


def test_importing_the_packages_is_cheap():
    code = "import sim, calibration, sys; print('torch' in sys.modules, 'numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_every_package_folder_says_what_it_holds():
    """A folder of modules is a package whose ``__init__`` docstring says what it offers (no
    namespace packages: a newcomer reads the folder's purpose in one place)."""
    import ast

    missing = []
    for top in ("sim", "calibration", "pipeline", "data_schemas"):
        for folder in sorted(p for p in (REPO / top).rglob("*") if p.is_dir() and any(p.glob("*.py"))):
            init = folder / "__init__.py"
            doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"))) if init.is_file() else None
            if not doc:
                missing.append(folder.relative_to(REPO).as_posix())
    assert missing == []


@pytest.mark.parametrize("package", ["pipeline.results", "pipeline.solving", "pipeline.streaming",
                                     "pipeline.frame_pipeline"])
def test_pipeline_packages_offer_what_they_list(package):
    import importlib

    pkg = importlib.import_module(package)
    for name in pkg.__all__:
        assert not isinstance(getattr(pkg, name), types.ModuleType), name
