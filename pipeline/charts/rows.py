"""Benchmark rows: reading a saved run, and the fields every reporting module reads from a row.

A results file is what ``iristac bench all`` writes (``{"machine", "quick", "sections": [{"bench",
"rows", ...}]}``) or one benchmark's ``--json`` output (``{"rows": [...]}``). A row is a dict:

``knob``, ``setting``      what was varied and to what;
``seconds``                the time of the setting (best of the repeats);
``error``, ``error_unit``  its error (``None``: not measured) and what the number is;
``bench``, ``machine``     the benchmark (the page's stage) and the machine it ran on;

and, where the benchmark records them: ``default`` (the shipped default), ``seconds_runs``
(every timed repeat: the spread :mod:`pipeline.bench.compare` reads as noise), ``error_runs``
(the error of every seed), ``capture_seconds``, ``threads``, ``device``, ``path``
(eager/fast/compiled), ``size`` and any other figure (shown on hover).

Examples
--------
>>> row_threads({"setting": "fast, 2 thread(s)"}), row_size({"knob": "live lut @ 320x240"})
(2, '320x240')
>>> row_path({"setting": "lstsq+dst (compiled)"}), is_default({"setting": "mlp 4 (default)"})
('compiled', True)
"""

from __future__ import annotations

import json
import re
import statistics
from pathlib import Path
from typing import Any

from pipeline.base.errors import UserError

__all__ = ["load_results", "result_rows", "row_threads", "row_size", "row_path", "row_device", "is_default",
           "row_key", "time_noise", "TIME_NOISE_FLOOR",
           "TIME_TOLERANCE", "ERROR_FLOOR"]

_SIZE = re.compile(r"@ ?(\d+x\d+)")
_THREADS = re.compile(r"(\d+) thread")
#: "default" as a word of a setting ("mlp 4 (default)", "off (edge detector, default)"), not "defaults"
#: nor "old default".
_DEFAULT = re.compile(r"(?<!old )\bdefault\b")


def load_results(path: str | Path) -> dict:
    """Read a saved benchmark run; a clear error names the file and what is wrong."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"{p}: no such file (expected the JSON that `iristac bench all` writes)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{p}: not a JSON benchmark run ({exc})") from None
    if not isinstance(data, dict) or not ("sections" in data or "rows" in data):
        keys = sorted(data)[:8] if isinstance(data, dict) else "-"
        raise UserError(f"{p}: expected an object with 'sections' (iristac bench all) or 'rows' (one benchmark's "
                        f"--json), got {type(data).__name__} with keys {keys}")
    if "sections" not in data:
        data = {"machine": data.get("machine", "unknown"), "quick": data.get("quick", False),
                "sections": [{"bench": data.get("bench", "run"), "rows": data["rows"], "seconds": None,
                              "error": None, "table": None}]}
    for i, s in enumerate(data["sections"]):
        for j, r in enumerate(s.get("rows") or []):
            for key in ("knob", "setting"):
                if key not in r:
                    raise UserError(f"{p}: sections[{i}] ({s.get('bench')}) rows[{j}] has no {key!r} field")
    return data


def result_rows(results: dict) -> list[dict[str, Any]]:
    """Every row of a run, each with its ``bench`` and ``machine``."""
    out = []
    for s in results.get("sections", []):
        for r in s.get("rows") or []:
            out.append(dict(r, bench=r.get("bench", s.get("bench", "")),
                            machine=r.get("machine", results.get("machine", "unknown"))))
    return out


def row_key(row: dict) -> tuple[str, str, str]:
    """What identifies a row across runs: (bench, knob, setting)."""
    return str(row.get("bench", "")), str(row["knob"]), str(row["setting"])


def row_size(row: dict) -> str | None:
    """Image size ``WxH`` of the row (its ``size`` field, else ``@ WxH`` in the knob)."""
    if row.get("size"):
        return str(row["size"])
    m = _SIZE.search(str(row.get("knob", "")))
    return m.group(1) if m else None


def row_threads(row: dict) -> int | None:
    """Threads of the row (its ``threads`` field, else ``N thread(s)`` in the setting)."""
    if row.get("threads") is not None:
        return int(row["threads"])
    m = _THREADS.search(str(row.get("setting", "")))
    return int(m.group(1)) if m else None


def row_path(row: dict) -> str | None:
    """``eager``, ``fast`` or ``compiled`` (its ``path`` field, else a word of the setting)."""
    if row.get("path"):
        return str(row["path"])
    s = str(row.get("setting", ""))
    for word in ("compiled", "fast", "eager"):
        if word in s:
            return word
    return None


def row_device(row: dict) -> str:
    """The device the row ran on: its ``device`` field, else ``cuda`` where the setting names
    CUDA or a GPU, else ``cpu``."""
    if row.get("device"):
        return str(row["device"])
    s = str(row.get("setting", "")).lower()
    return "cuda" if ("cuda" in s or "gpu" in s) else "cpu"


def is_default(row: dict) -> bool:
    """Whether the row is the shipped default (its ``default`` field, else the word in its setting).

    >>> is_default({"setting": "far (defaults)"}), is_default({"setting": "near votes (old default)"})
    (False, False)
    """
    if "default" in row:
        return bool(row["default"])
    return bool(_DEFAULT.search(str(row.get("setting", ""))))


#: Noise floors shared by ``iristac bench compare`` and the sentences under the charts: a time
#: change smaller than TIME_NOISE_FLOOR (relative; or twice the repeats' spread) is noise, as is
#: an error change under ERROR_FLOOR; rows without recorded repeats use TIME_TOLERANCE.
TIME_NOISE_FLOOR = 0.10
TIME_TOLERANCE = 0.25
ERROR_FLOOR = 0.01


def time_noise(row: dict) -> float | None:
    """Relative spread of a row's timed repeats, ``(median - best) / best`` (None: none recorded).

    The noise of a best-of-repeats time: how far the timings wander while the row runs. The
    sentences under the charts and ``iristac bench compare`` both read it.

    Examples
    --------
    >>> round(time_noise({"seconds_runs": [1.0, 1.1, 1.3]}), 3), time_noise({"seconds": 1.0})
    (0.1, None)
    """
    runs = [float(t) for t in row.get("seconds_runs") or [] if t is not None and t > 0]
    if len(runs) < 2:
        return None
    best = min(runs)
    return (statistics.median(runs) - best) / best
