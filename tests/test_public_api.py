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
