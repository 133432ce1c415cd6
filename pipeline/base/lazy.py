"""Names of a package imported on first use (PEP 562), so that importing the package is cheap.

Why: ``pipeline.normals`` and ``pipeline.depth`` re-export solvers whose modules load torch and
scipy.sparse (about 1.5 s together); the live fast paths import only their own submodules, and
a camera's first result then comes about a second sooner (docs/live.md, "Start-up").
"""

from __future__ import annotations

import importlib

__all__ = ["lazy_names"]


def lazy_names(package: str, where: dict[str, str], namespace: dict):
    """``(__getattr__, __dir__)`` for ``package``: ``where`` maps a name to its submodule.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    where : dict
        Public name -> submodule (relative to ``package``) that defines it.
    namespace : dict
        The package's ``globals()``: a name, once imported, is stored there (later lookups
        are plain attribute reads).

    Examples
    --------
    >>> ns = {}
    >>> getattr_, dir_ = lazy_names("json", {"JSONDecoder": "decoder"}, ns)
    >>> getattr_("JSONDecoder").__name__, "JSONDecoder" in ns, "JSONDecoder" in dir_()
    ('JSONDecoder', True, True)
    """

    def __getattr__(name: str):
        if name in where:
            value = getattr(importlib.import_module(f"{package}.{where[name]}"), name)
            namespace[name] = value
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__():
        return sorted(set(namespace) | set(where))

    return __getattr__, __dir__
