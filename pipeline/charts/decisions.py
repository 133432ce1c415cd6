"""The decisions a user makes, each as a chart built from benchmark rows, with a sentence read from the data.

:data:`VIEWS` lists the questions (which solver for live work, how many rays, which lighting
mode, ...). Each view picks its rows by their fields (``knob``, ``size``, ``threads``,
``device``, ``path``...), so a new row with those fields (a GPU row, another thread count)
lands in the right chart without a code change. Rows that no view takes get a chart per
knob (two points or more with an error and a time) or go into a table
(:func:`tables`): a knob with a single point, or a time without an error.

Every chart's sentence is computed (:mod:`pipeline.charts.sentences`): the most accurate
setting within a time budget, the cheapest within an error target, the front's two ends, a
contrast between two settings, or what one step (eager to fast, one thread to all) buys.

Examples
--------
>>> rows = [{"bench": "live", "knob": "live lut @ 320x240", "setting": "fast, 1 thread(s)", "error": 0.07,
...          "error_unit": "deg", "seconds": 0.004, "machine": "m", "default": True},
...         {"bench": "live", "knob": "live mlp @ 320x240", "setting": "fast, 1 thread(s)", "error": 0.7,
...          "error_unit": "deg", "seconds": 0.01, "machine": "m"}]
>>> [c.key for c in build_charts(rows)]
['live-320x240']
>>> build_charts(rows)[0].sentence.startswith("Within a 60 fps camera's frame time (16.7 ms)")
True
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Callable

from pipeline.charts import sentences as say
from pipeline.charts.model import Chart, Point, format_seconds
from pipeline.charts.rows import is_default, row_device, row_path, row_size, row_threads, time_noise

__all__ = ["View", "VIEWS", "build_charts", "tables", "summary_charts", "row_point", "SUMMARY"]

Row = dict


@dataclass
class View:
    """One question, answered by one chart (or one per value of ``split``)."""

    key: str
    group: str
    title: str
    match: Callable[[Row], bool]
    label: Callable[[Row], str]
    series: Callable[[Row], str] = lambda r: ""
    name: Callable[[Row], str] | None = None
    x: str = "seconds"
    x_label: str = "seconds"
    front: str = "all"
    split: Callable[[Row], str] | None = None
    budget: tuple[float, str] | None = None
    target: tuple[float, str] | None = None
    sentence: Callable[[Chart], str] = say.front
    note: str = ""
    keep: Callable[[list[Row]], list[Row]] = lambda rows: rows
    connect: bool = False


def _knob(pattern: str) -> Callable[[Row], bool]:
    rx = re.compile(pattern)
    return lambda r: bool(rx.search(str(r.get("knob", ""))))


def _group_of(r: Row, pattern: str) -> str:
    m = re.search(pattern, str(r.get("knob", "")))
    return m.group(1) if m else str(r.get("knob", ""))


def _short_rays(n) -> str:
    n = float(n)
    for div, unit in ((1e6, "M"), (1e3, "k")):
        if n >= div:
            return f"{n / div:.3g}{unit}"
    return f"{n:g}"


def _threads_label(r: Row) -> str:
    t = row_threads(r)
    dev = row_device(r)
    base = f"{t} thread{'s' if t != 1 else ''}" if t is not None else ""
    return f"{dev} {base}".strip() if dev != "cpu" else base


def _multi(rows: list[Row], key: Callable[[Row], object], least: int = 2) -> list[Row]:
    """The rows whose series (``key``) has at least ``least`` distinct labels."""
    counts: dict = {}
    for r in rows:
        counts.setdefault(key(r), set()).add(r["_label"])
    return [r for r in rows if len(counts[key(r)]) >= least]


def _best_per(rows: list[Row], field_name: str) -> list[Row]:
    """Per value of ``field_name``, the most accurate row, and the shipped default's row."""
    best: dict = {}
    for r in rows:
        k = r.get(field_name)
        if k not in best or r["error"] < best[k]["error"]:
            best[k] = r
    keep = {id(r) for r in best.values()} | {id(r) for r in rows if is_default(r)}
    return [r for r in rows if id(r) in keep]


def _live_series(r: Row) -> str:
    return _group_of(r, r"^live (.+?) @")


def _size_series(r: Row) -> str:
    base = re.sub(r"\s*@ ?\d+x\d+", "", str(r["knob"]))
    return f"{base}: {r['setting']}" if r.get("bench") != "live" else f"{base} ({row_path(r)})"


def _thread_series(r: Row) -> str:
    path = row_path(r)
    return f"{r['knob']} ({path})" if path else str(r["knob"])


def _path_series(r: Row) -> str:
    base = re.sub(r"\((eager|compiled|fast)[^)]*\)|eager|fast|compiled|,\s*\d+ thread\(s\)", "",
                  f"{r['knob']}: {r['setting']}")
    base = base.replace(", )", ")").replace("()", "").replace("lstsq (far field, )", "lstsq (far field)")
    return re.sub(r"\s+", " ", base).strip(" :,")


def _path_label(r: Row) -> str:
    return row_path(r) or "eager"


def _rays_cost(p: Point) -> float:
    return float(p.hover.get("rays", "inf"))


def _fewest_rays(c: Chart) -> str:
    return say.within_target(c, cost=_rays_cost, cost_name="setting with the fewest rays")


LIVE_FPS = 60.0
FLUX_TARGET = 1.0

VIEWS: list[View] = [
    View("live", "Live reconstruction", "Which solver for live work at {split}?",
         match=lambda r: r.get("bench") == "live" and row_path(r) in ("fast", None) and row_size(r) is not None,
         split=row_size, series=_live_series, label=_threads_label,
         x_label="seconds per frame (uint8 frames to heights)",
         budget=(1.0 / LIVE_FPS, f"{LIVE_FPS:g} fps camera"), sentence=say.within_budget,
         note="Errors: near field on the bench's 8-sector sphere (point: 24 LEDs), LUT, MLP and the convolutional "
              "networks (conv; conv-fast, on the frame shrunk by 2) on rendered trichromatic presses they were not "
              "calibrated on (iristac bench live)."),
    View("batch", "Batch processing", "What does a recording cost a frame, by solver, length and threads?",
         match=lambda r: r.get("bench") == "batch", series=lambda r: _group_of(r, r"^batch (.+?) @"),
         label=lambda r: str(r["setting"]).replace(" thread(s)", " thr").replace(" frames", " fr"),
         x_label="seconds per frame (a recording on disk to results on disk)", front="none",
         sentence=lambda c: say.front(c),
         note="iristac bench batch: the batch command in a new process on recordings of each length, beside "
              "the live path's figure for the same solver and threads (docs/reconstruction.md, Batch processing)."),
    View("rays-flux", "Ray tracer", "How many rays does the lens designer need for 1 % flux error?",
         match=_knob(r"^lens design: flux error"), series=lambda r: str(r.get("sampler", "")),
         label=lambda r: _short_rays(r.get("rays", 0)), x_label="seconds per design evaluation (24 LEDs)",
         target=(FLUX_TARGET, "1 % flux error"), sentence=_fewest_rays, connect=True,
         note="Flux: the fraction of the LEDs' light on the imaging plane, the designer's objective; error: RMS over "
              "seeds against 4e6 Sobol rays."),
    View("rays-cv", "Ray tracer", "How many rays for the uniformity (CV) a lens design is held to?",
         match=_knob(r"^lens design: uniformity error"), series=lambda r: str(r.get("sampler", "")),
         label=lambda r: _short_rays(r.get("rays", 0)), x_label="seconds per design evaluation (24 LEDs)",
         target=(FLUX_TARGET, "1 % CV error"), sentence=_fewest_rays, connect=True),
    View("rays-image", "Ray tracer", "How many rays for an illumination image (per-pixel error)?",
         match=_knob(r"^rays x sampler$"), series=lambda r: str(r["setting"]).split()[0],
         label=lambda r: _short_rays(str(r["setting"]).split()[-1].replace(",", "")),
         x_label="seconds per trace (one LED, 60 x 60 px)", target=(0.01, "1 % per-pixel error"),
         sentence=_fewest_rays, connect=True,
         note="Error: relative L2 of LED 0's 60 x 60 px irradiance image against 4e6 Sobol rays (which bounds what "
              "can be measured from below)."),
    View("modes-capture", "Lighting mode", "What does a lighting mode buy, against capture time?",
         match=_knob(r"^lighting mode x solver"), series=lambda r: str(r.get("solver", "")),
         label=lambda r: str(r["setting"]), x="capture_seconds", name=lambda r: str(r["setting"]),
         keep=lambda rows: _best_per(rows, "mode"),
         x_label="capture seconds per contact (emulated ring + camera)",
         sentence=lambda c: say.contrast(c, "point", "trichromatic", "capture time"),
         note="Each mode with its most accurate solver (and the shipped default where one is ringed); every "
              "solver: the chart against reconstruction time."),
    View("modes-recon", "Lighting mode", "What does a lighting mode buy, against reconstruction time?",
         match=_knob(r"^lighting mode x solver"), series=lambda r: str(r.get("solver", "")),
         label=lambda r: str(r.get("mode", r["setting"])), x_label="seconds to reconstruct one capture",
         name=lambda r: str(r["setting"]),
         sentence=lambda c: say.contrast(c, "point", "trichromatic", "reconstruction time")),
    View("solver", "Normal solver", "Which normal solver ({split})?",
         match=lambda r: _knob(r"^(normal solver @|PS solver)")(r) and r.get("error") is not None,
         split=lambda r: _group_of(r, r"^(?:normal solver @ ?|PS solver, )(.+)$"),
         label=lambda r: str(r["setting"]).replace(" (masked)", ""), x_label="seconds per frame"),
    View("integrator", "Depth integrator", "Which depth integrator ({split})?",
         match=_knob(r"^integrator"), split=row_size, label=lambda r: str(r["setting"]),
         x_label="seconds per frame"),
    View("model", "Light model", "Which light model ({split})?",
         match=_knob(r"^calibration model"), split=lambda r: _group_of(r, r"^calibration model \((.+)\)$"),
         label=lambda r: str(r["setting"]).replace(" (defaults)", ""), x_label="seconds to fit"),
    View("multisource", "Ray tracer", "All 24 LEDs: trace each, rotate the hits, or rotate the image?",
         match=_knob(r"^multi-source method$"), label=lambda r: str(r["setting"]),
         x_label="seconds for 24 LEDs"),
    View("intersection", "Ray tracer", "Lens intersection: which method, how many iterations?",
         match=lambda r: _knob(r"^intersection iterations")(r) and r.get("error") is not None,
         series=lambda r: str(r["setting"]).rsplit(" x", 1)[0].replace(" (checked)", "").replace(
             " (monotone Newton)", "") + " " + _group_of(r, r"\((\w+)\)$"),
         label=lambda r: "x" + str(r["setting"]).rsplit(" x", 1)[-1], x_label="seconds (1e5 rays, torch)"),
    View("path", "Eager or fast path", "What does the fast (compiled, precomputed) path buy?",
         match=lambda r: row_path(r) is not None and row_threads(r) in (None, 1) and row_device(r) == "cpu",
         series=_path_series, label=_path_label, front="none", connect=True, x_label="seconds per frame",
         keep=lambda rows: _multi(rows, lambda r: r["_series"]),
         sentence=lambda c: say.steps(c, "eager", ("fast", "compiled"))),
    View("threads", "Threads and device", "What do more threads or another device buy?",
         match=lambda r: row_threads(r) is not None or r.get("device") not in (None, "cpu"),
         series=_thread_series, label=_threads_label, front="none", connect=True, x_label="seconds per frame",
         keep=lambda rows: _multi(rows, lambda r: r["_series"]), sentence=say.threads),
    View("size", "Image size", "What does a bigger image cost?",
         match=lambda r: row_size(r) is not None and r.get("bench") in ("live", "reconstruct")
         and str(r.get("error_unit")) == "deg" and row_path(r) != "eager" and row_threads(r) in (None, 1)
         and "compiled" not in str(r["setting"]) and "ratio" not in str(r["setting"]),
         series=_size_series, label=lambda r: row_size(r) or "", front="none", connect=True,
         x_label="seconds per frame",
         keep=lambda rows: _multi(rows, lambda r: r["_series"]), sentence=say.sizes),
]

#: Keys of the charts in the summary figure, in order (at most 6).
SUMMARY = ("live-320x240", "rays-flux", "modes-capture", "solver-320x240", "model-split-on-detected-circles",
           "integrator-320x240")

#: Knobs shown as tables only, with why: their error does not trade against time.
TABLE_ONLY = ((r"^render ", "the error is float32 against float64 rendering (a precision check), about the "
                            "same for every setting: the time is the figure"),
              (r"^capture:", "no frame was mislabelled in any setting: the time is the figure"))


def _fmt_exact(v) -> str:
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def row_point(r: Row, x_field: str, label: str, series: str) -> Point:
    """A chart point of row ``r``, its exact figures for the hover."""
    x = float(r[x_field])
    hover = {"setting": f"{r['knob']}: {r['setting']}",
             "error": f"{_fmt_exact(r['error'])} {r.get('error_unit') or ''}".strip()}
    hover[x_field.replace("_", " ")] = f"{_fmt_exact(x)} s ({format_seconds(x)})"
    if x_field != "seconds" and r.get("seconds") is not None:
        hover["seconds"] = f"{_fmt_exact(float(r['seconds']))} s"
    runs = r.get("seconds_runs")
    if runs:
        hover["repeats"] = f"{len(runs)} timed, spread {format_seconds(min(runs))} – {format_seconds(max(runs))}"
    for k, v in r.items():
        if k in ("knob", "setting", "error", "error_unit", "seconds", "seconds_runs", "machine", "bench", x_field,
                 "error_runs") or k.startswith("_") or isinstance(v, (list, dict)) or v is None:
            continue
        hover[k.replace("_", " ")] = _fmt_exact(v)
    hover["stage"] = str(r.get("bench", ""))
    hover["machine"] = str(r.get("machine", ""))
    noise = time_noise(r) if x_field == "seconds" else None
    return Point(x, float(r["error"]), label, series, is_default(r), hover, x_noise=noise)


def _plottable(r: Row, x_field: str) -> bool:
    return r.get("error") is not None and r.get(x_field) is not None


def _unit(rows: list[Row]) -> str:
    units = sorted({str(r.get("error_unit") or "") for r in rows})
    return units[0] if len(units) == 1 else ", ".join(units)


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")


def _chart(v: View, rows: list[Row], split: str | None) -> Chart | None:
    for r in rows:
        r["_label"], r["_series"] = v.label(r), v.series(r)
    rows = v.keep(rows)
    if len(rows) < 2:
        return None
    key = v.key + (f"-{_slug(split)}" if split else "")
    unit = _unit(rows)
    y_label = (f"error: {unit}" if "(" in unit else f"error ({unit})") if unit else "error"
    pts = [row_point(r, v.x, r["_label"], r["_series"]) for r in rows]
    if v.name:
        for p, r in zip(pts, rows):
            p.name = v.name(r)
    c = Chart(key, v.title.format(split=split or ""), v.x_label, y_label, pts, front=v.front, budget=v.budget,
              target=v.target, note=v.note, stages=tuple(sorted({str(r.get("bench", "")) for r in rows})),
              group=v.group, connect=v.connect)
    c.sentence = v.sentence(c)
    return c


def _view_charts(v: View, rows: list[Row]) -> tuple[list[Chart], set[int]]:
    """The charts of one view, and the ids of the rows it took."""
    taken = [r for r in rows if v.match(r) and _plottable(r, v.x)]
    by_unit: dict[str, list[Row]] = {}
    for r in taken:
        by_unit.setdefault(str(r.get("error_unit") or ""), []).append(r)
    charts = []
    for unit, unit_rows in by_unit.items():
        splits: dict = {}
        for r in unit_rows:
            splits.setdefault(v.split(r) if v.split else None, []).append(dict(r))
        for split, srows in splits.items():
            c = _chart(v, srows, split)
            if c is not None:
                if len(by_unit) > 1:
                    c.key += "-" + _slug(unit)
                charts.append(c)
    return charts, {id(r) for r in taken}


def _table_only(r: Row) -> bool:
    return any(re.search(p, str(r.get("knob", ""))) for p, _ in TABLE_ONLY)


def build_charts(rows: list[Row]) -> list[Chart]:
    """Every chart the rows support: the views first, then one per remaining knob."""
    charts: list[Chart] = []
    used: set[int] = set()
    for v in VIEWS:
        cs, ids = _view_charts(v, rows)
        charts += cs
        used |= ids
    by_knob: dict[tuple, list[Row]] = {}
    for r in rows:
        if id(r) not in used and _plottable(r, "seconds") and not _table_only(r):
            by_knob.setdefault((r.get("bench", ""), r["knob"]), []).append(r)
    for (bench, knob), krows in by_knob.items():
        if len(krows) >= 2:
            v = View(f"other-{bench}", f"Other measurements ({bench})", str(knob), match=lambda r: True,
                     label=lambda r: str(r["setting"]), x_label="seconds")
            c = _chart(v, [dict(r) for r in krows], None)
            if c is not None:
                c.key = f"{bench}-{_slug(str(knob))}"
                charts.append(c)
    return charts


def tables(rows: list[Row], charts: list[Chart]) -> list[dict]:
    """Knobs no chart shows (a single point, no error or no time, or table-only), as tables:
    ``[{"bench", "knob", "why", "rows"}]``."""
    shown = {(p.hover.get("stage"), p.hover.get("setting")) for c in charts for p in c.points}
    out: dict[tuple, dict] = {}
    for r in rows:
        if (str(r.get("bench", "")), f"{r['knob']}: {r['setting']}") in shown:
            continue
        key = (r.get("bench", ""), r["knob"])
        why = next((w for p, w in TABLE_ONLY if re.search(p, str(r["knob"]))), None)
        t = out.setdefault(key, {"bench": key[0], "knob": key[1], "why": why, "rows": []})
        t["rows"].append(r)
    for t in out.values():
        if t["why"] is None:
            t["why"] = ("a single setting" if len(t["rows"]) == 1 else
                        "time only (no error measured)" if all(r.get("error") is None for r in t["rows"]) else
                        "not charted: no error or no time for these settings")
    return list(out.values())


def summary_charts(charts: list[Chart]) -> list[Chart]:
    """The charts of the summary figure (:data:`SUMMARY`, those present, at most 6)."""
    by_key = {c.key: c for c in charts}
    return [by_key[k] for k in SUMMARY if k in by_key][:6]


@dataclass
class Overview:
    """What a page or a markdown report needs: charts, tables, the machines."""

    charts: list[Chart]
    tables: list[dict]
    machines: list[str] = field(default_factory=list)


def overview(rows: list[Row]) -> Overview:
    """Charts and tables of ``rows``."""
    charts = build_charts(rows)
    return Overview(charts, tables(rows, charts), sorted({str(r.get("machine", "")) for r in rows}))
