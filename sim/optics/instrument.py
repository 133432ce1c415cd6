"""Counters that prove which effects ran: a disabled effect is never computed.

Every effect's code path calls :func:`count` with its name; tests reset the counters, trace
a scene and check that only the scene's effects were counted. Counting is one dict update
per call (per chunk), not per ray, so it costs nothing measurable.

Examples
--------
>>> reset(); count("fresnel"); count("fresnel"); snapshot()["fresnel"]
2
"""

from __future__ import annotations

import sys
from collections import Counter

__all__ = ["count", "reset", "snapshot"]

_COUNTS: Counter = Counter()


def count(name: str, n: int = 1) -> None:
    """Record that the code path ``name`` ran ``n`` times.

    A no-op inside ``torch.compile`` (a traced side effect would run once, at tracing). The
    compiled kernel counts its effects where it is called (:mod:`sim.optics.engine`).
    """
    torch = sys.modules.get("torch")  # never imported for this: the kernel's path runs without torch
    if torch is not None and torch.compiler.is_compiling():
        return
    _COUNTS[name] += n


def reset() -> None:
    """Zero every counter."""
    _COUNTS.clear()


def snapshot() -> dict[str, int]:
    """A copy of the counters (missing names are zero)."""
    return dict(_COUNTS)
