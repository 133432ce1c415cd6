"""``iristac bench compare OLD.json NEW.json``: the rows that got slower or less accurate, beyond the noise.

Rows of the two runs are matched by (bench, knob, setting). How noise is estimated:

time
    A row's time is the best of its timed repeats; the benchmarks keep every repeat
    (``seconds_runs``). The noise of a run's best time is taken as the spread of its repeats,
    ``(median - best) / best``: how far a run's timings wander while it runs (other processes,
    caches, frequency). A row is *slower* when ``new / old - 1`` exceeds twice the larger of
    the two runs' spreads, and never less than ``--time-floor`` (default 10 %: between two runs
    the load changes more than within one). A row without recorded repeats is held to
    ``--time-tolerance`` (default 25 %). Times of two different machines are not compared
    (``--across-machines`` compares them anyway).
error
    Errors come from seeded data: the same code on the same libraries gives the same error,
    so any growth is the change's. A row is *less accurate* when ``new - old`` exceeds
    ``--error-floor`` (default 1 %) of the old error, twice the spread of its seeds where it
    has several (``error_runs``), and a millionth of the largest error of its knob (so float
    round-off at 1e-14 mm is not a regression).

The same tests in the other direction list what got faster or more accurate. Exit status 1
when a row regressed (for a CI gate), 0 otherwise. The spread of the repeats is the noise
*within* a run; on a loaded machine the load also changes *between* runs, which no repeat
sees: a run whose recorded load average exceeds its cores is named in a warning (measured
here: two back-to-back quick live runs under load 5 on 2 cores flagged one row of twelve
1.6x slower; compare runs from a quiet machine).

Python: :func:`compare_runs`.
"""

from __future__ import annotations

import statistics
from dataclasses import asdict, dataclass

from pipeline.charts.model import format_seconds, format_value
from pipeline.charts.rows import (
    ERROR_FLOOR,
    TIME_NOISE_FLOOR,
    TIME_TOLERANCE,
    load_results,
    result_rows,
    row_key,
    time_noise,
)

__all__ = ["add_arguments", "run", "format_table", "compare_runs", "Change", "time_noise"]


def add_arguments(parser) -> None:
    parser.add_argument("old", metavar="OLD.json", help="the earlier run (iristac bench all's JSON)")
    parser.add_argument("new", metavar="NEW.json", help="the later run")
    parser.add_argument("--time-floor", type=float, default=TIME_NOISE_FLOOR,
                        help=f"smallest relative slow-down flagged for rows with recorded repeats (default {TIME_NOISE_FLOOR})")
    parser.add_argument("--time-tolerance", type=float, default=TIME_TOLERANCE,
                        help=f"relative slow-down flagged for rows without recorded repeats (default {TIME_TOLERANCE})")
    parser.add_argument("--error-floor", type=float, default=ERROR_FLOOR,
                        help=f"smallest relative error growth flagged (default {ERROR_FLOOR})")
    parser.add_argument("--across-machines", action="store_true",
                        help="compare times even when the two runs were measured on different machines")


@dataclass
class Change:
    """One row's change beyond the noise."""

    kind: str          # "slower", "faster", "less accurate", "more accurate"
    bench: str
    knob: str
    setting: str
    old: float
    new: float
    change: float      # new / old - 1
    threshold: float   # the relative change that counted as noise
    noise: str         # how the threshold was set

    def regression(self) -> bool:
        return self.kind in ("slower", "less accurate")


def _time_change(old: dict, new: dict, opts: dict) -> Change | None:
    a, b = old.get("seconds"), new.get("seconds")
    if not a or not b or a <= 0 or b <= 0:
        return None
    spreads = [s for s in (time_noise(old), time_noise(new)) if s is not None]
    if len(spreads) == 2:
        thr = max(opts["time_floor"], 2.0 * max(spreads))
        how = f"twice the repeats' spread of {100 * max(spreads):.0f} %, floor {100 * opts['time_floor']:.0f} %"
    else:
        thr, how = opts["time_tolerance"], "no repeats recorded: the tolerance"
    change = b / a - 1.0
    # faster by the same margin in the other direction: a / b - 1 > thr
    if change > thr:
        kind = "slower"
    elif a / b - 1.0 > thr:
        kind = "faster"
    else:
        return None
    return Change(kind, *row_key(new), a, b, change, thr, how)


def _error_change(old: dict, new: dict, knob_max: float, opts: dict) -> Change | None:
    a, b = old.get("error"), new.get("error")
    if a is None or b is None:
        return None
    a, b = float(a), float(b)
    limits = {"floor": opts["error_floor"] * abs(a), "round-off": 1e-6 * knob_max}
    seeds = [float(e) for e in old.get("error_runs") or [] if e is not None]
    if len(seeds) > 1:
        limits["seed spread"] = 2.0 * statistics.pstdev(seeds)
    how, margin = max(limits.items(), key=lambda kv: kv[1])
    if b - a > margin:
        kind = "less accurate"
    elif a - b > margin:
        kind = "more accurate"
    else:
        return None
    change = b / a - 1.0 if a else float("inf")
    return Change(kind, *row_key(new), a, b, change, margin / abs(a) if a else 0.0, how)


def compare_runs(old: dict, new: dict, *, time_floor: float = TIME_NOISE_FLOOR, time_tolerance: float = TIME_TOLERANCE,
                 error_floor: float = ERROR_FLOOR, across_machines: bool = False) -> dict:
    """Changes between two runs (dicts as ``iristac bench all`` writes them).

    Returns ``{"changes": [Change...], "regressions": n, "only_old": [...], "only_new": [...],
    "matched": n, "machines": (old, new), "times_compared": bool}``.
    """
    opts = {"time_floor": time_floor, "time_tolerance": time_tolerance, "error_floor": error_floor}
    old_rows = {row_key(r): r for r in result_rows(old)}
    new_rows = {row_key(r): r for r in result_rows(new)}
    knob_max: dict = {}
    for r in old_rows.values():
        if r.get("error") is not None:
            k = r["knob"]
            knob_max[k] = max(knob_max.get(k, 0.0), abs(float(r["error"])))
    machines = (str(old.get("machine", "")), str(new.get("machine", "")))
    times = across_machines or machines[0] == machines[1]
    changes = []
    for key in old_rows.keys() & new_rows.keys():
        o, n = old_rows[key], new_rows[key]
        found = [_error_change(o, n, knob_max.get(o["knob"], 0.0), opts)]
        if times:
            found.append(_time_change(o, n, opts))
        changes += [c for c in found if c is not None]
    changes.sort(key=lambda c: (not c.regression(), c.kind, c.bench, c.knob, c.setting))
    return {"changes": changes, "regressions": sum(c.regression() for c in changes),
            "only_old": sorted(old_rows.keys() - new_rows.keys()),
            "only_new": sorted(new_rows.keys() - old_rows.keys()),
            "matched": len(old_rows.keys() & new_rows.keys()), "machines": machines, "times_compared": times}


def load_warning(run: dict, name: str) -> str | None:
    """A warning when ``run`` recorded a load average above the cores its machine string names."""
    import re

    load = run.get("load_average") or []
    m = re.search(r"(\d+) cores", str(run.get("machine", "")))
    if not load or not m or max(load) <= int(m.group(1)):
        return None
    return (f"{name} was measured under load (load average up to {max(load):.1f} on {m.group(1)} cores): its times "
            f"drift more between runs than its repeats show")


def run(args) -> dict:
    old, new = load_results(args.old), load_results(args.new)
    res = compare_runs(old, new, time_floor=args.time_floor, time_tolerance=args.time_tolerance,
                       error_floor=args.error_floor, across_machines=args.across_machines)
    res["warnings"] = [w for w in (load_warning(old, "OLD"), load_warning(new, "NEW")) if w]
    res["changes"] = [asdict(c) | {"regression": c.regression()} for c in res["changes"]]
    res["exit_code"] = 1 if res["regressions"] else 0
    return res


def _change_text(c: dict) -> str:
    if c["kind"] in ("slower", "faster"):
        ratio = c["new"] / c["old"] if c["kind"] == "slower" else c["old"] / c["new"]
        return (f"{format_seconds(c['old'])} -> {format_seconds(c['new'])}: {ratio:.2f}x {c['kind']}, beyond "
                f"{1 + c['threshold']:.2f}x ({c['noise']})")
    return (f"{format_value(c['old'])} -> {format_value(c['new'])}: {100 * c['change']:+.1f} %, beyond "
            f"{100 * c['threshold']:.1f} % ({c['noise']})")


def format_table(result: dict) -> str:
    lines = [f"{result['matched']} rows in both runs; {result['regressions']} regressed beyond the noise"]
    if not result["times_compared"]:
        lines.append(f"times not compared: measured on different machines ({result['machines'][0]} / "
                     f"{result['machines'][1]}); --across-machines compares them")
    lines += [f"warning: {w}" for w in result.get("warnings", [])]
    for c in result["changes"]:
        mark = "REGRESSION" if c["regression"] else "improved"
        lines.append(f"{mark:>10}  {c['kind']:<13} {c['bench']}: {c['knob']}: {c['setting']}: {_change_text(c)}")
    for label, keys in (("only in OLD", result["only_old"]), ("only in NEW", result["only_new"])):
        if keys:
            lines.append(f"{len(keys)} rows {label}: " + "; ".join(f"{b}: {k}: {s}" for b, k, s in keys[:8])
                         + (" ..." if len(keys) > 8 else ""))
    return "\n".join(lines)
