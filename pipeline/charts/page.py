"""An offline interactive page of charts (Plotly): hover for the exact figures, a stage selector.

Plotly because its Python package ships the whole JavaScript library (``plotly.min.js``,
read through the public :func:`plotly.offline.get_plotlyjs`), so the page needs no network:
the library is written beside the page (``js="beside"``: one file for every page of a
folder, unchanged between runs) or embedded in it (``js="inline"``: one file to send). Its
log axes, hover labels and PNG export come without code of ours. The figures are plain
JSON (data and layout) drawn by ``Plotly.newPlot``; labels are placed by
:func:`pipeline.charts.labels.place_labels`, as in the PNGs.

When every chart has been drawn the page sets ``data-rendered`` on ``<body>`` to the number
of charts (the browser test waits for it).

Examples
--------
>>> import tempfile, pathlib
>>> from pipeline.charts.model import Chart, Point
>>> c = Chart("k", "Which?", "seconds", "error (deg)", [Point(0.01, 1.0, "a"), Point(0.1, 0.1, "b")],
...           stages=("live",))
>>> out = write_page(pathlib.Path(tempfile.mkdtemp()) / "p.html", [c], title="T")
>>> sorted(p.name for p in out.parent.iterdir())[0].startswith("p.html"), 'id="chart-k"' in out.read_text()
(True, True)
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Sequence

from pipeline.charts.labels import chart_placement, limit_boxes
from pipeline.charts.model import (
    MARKERS,
    Chart,
    Table,
    chart_axes,
    chart_fronts,
    log_ticks,
    plot_value,
    point_label,
    tick_labels,
)

__all__ = ["write_page", "chart_figure", "chart_html", "library_tag", "render_script", "WIDTH", "HEIGHT"]

#: Chart size on the page, px, and its margins.
WIDTH, HEIGHT = 860, 430
MARGIN = {"l": 70, "r": 24, "t": 34, "b": 0}
LABEL_PX = 11.0
FONT = "Liberation Sans, Arial, Helvetica, sans-serif"


def _legend_rows(chart: Chart) -> int:
    names = [s for s in chart.series_names() if s] + ["Pareto front", "shipped default"]
    width = sum(0.62 * 12 * len(n) + 46 for n in names)
    return max(1, math.ceil(width / (WIDTH - 60)))


def _hover(p) -> str:
    return "<br>".join(f"<b>{html.escape(k)}</b>: {html.escape(v)}" for k, v in p.hover.items())


def _ticks(lo: float, hi: float, seconds: bool) -> dict:
    vals = log_ticks(lo, hi)
    return {"tickvals": vals, "ticktext": tick_labels(vals, seconds)}


def _traces(chart: Chart, axes) -> list[dict]:
    fx = [plot_value(p.x, axes.x_floor) for p in chart.points]
    fy = [plot_value(p.y, axes.y_floor) for p in chart.points]
    traces = []
    for k, front in enumerate(chart_fronts(chart)):
        if len(front) > 1:
            colour = "#555555"
            if chart.front == "series":
                colour = MARKERS[chart.series_names().index(chart.points[front[0]].series) % len(MARKERS)][0]
            traces.append({"type": "scatter", "mode": "lines", "x": [fx[i] for i in front],
                           "y": [fy[i] for i in front],
                           "line": {"shape": "hv", "dash": "dash", "color": colour, "width": 1.5},
                           "name": "Pareto front", "legendgroup": "front", "showlegend": k == 0,
                           "hoverinfo": "skip"})
    for i, s in enumerate(chart.series_names()):
        colour, _, symbol = MARKERS[i % len(MARKERS)]
        idx = [j for j, p in enumerate(chart.points) if p.series == s]
        traces.append({"type": "scatter", "mode": "lines+markers" if chart.connect else "markers",
                       "line": {"color": colour, "width": 1}, "name": s or "settings", "showlegend": bool(s),
                       "x": [fx[j] for j in idx], "y": [fy[j] for j in idx],
                       "marker": {"color": colour, "symbol": symbol, "size": 10,
                                  "line": {"color": "white", "width": 1}},
                       "customdata": [_hover(chart.points[j]) for j in idx],
                       "hovertemplate": "%{customdata}<extra></extra>"})
    d = [j for j, p in enumerate(chart.points) if p.default]
    if d:
        traces.append({"type": "scatter", "mode": "markers", "name": "shipped default", "x": [fx[j] for j in d],
                       "y": [fy[j] for j in d], "hoverinfo": "skip",
                       "marker": {"symbol": "circle-open", "size": 22, "color": "black", "line": {"width": 2}}})
    for limit, vertical in ((chart.budget, True), (chart.target, False)):
        if limit:
            lo, hi = ((10 ** axes.y_lo, 10 ** axes.y_hi) if vertical else (10 ** axes.x_lo, 10 ** axes.x_hi))
            xy = ([limit[0], limit[0]], [lo, hi]) if vertical else ([lo, hi], [limit[0], limit[0]])
            traces.append({"type": "scatter", "mode": "lines", "x": xy[0], "y": xy[1], "showlegend": False,
                           "hoverinfo": "skip", "line": {"dash": "dot", "color": "#aa3333", "width": 1.2}})
    return traces


def _annotations(chart: Chart, axes, plot_w: float, plot_h: float) -> list[dict]:
    texts = [point_label(p) for p in chart.points]
    pl = chart_placement(chart, plot_w, plot_h, LABEL_PX)
    out = []
    for p, t, off, lead in zip(chart.points, texts, pl.offsets, pl.leaders):
        out.append({"x": math.log10(plot_value(p.x, axes.x_floor)), "y": math.log10(plot_value(p.y, axes.y_floor)),
                    "text": html.escape(t), "showarrow": True, "ax": float(off[0]), "ay": float(-off[1]),
                    "axref": "pixel", "ayref": "pixel", "arrowhead": 0, "arrowwidth": 0.8, "standoff": 0,
                    "arrowcolor": "#888888" if lead else "rgba(0,0,0,0)", "xanchor": "center", "yanchor": "middle",
                    "font": {"size": LABEL_PX, "family": FONT}, "captureevents": False, "name": "label"})
    for key, b in limit_boxes(chart, axes, plot_w, plot_h, LABEL_PX).items():
        text = (chart.budget if key == "budget" else chart.target)[1]
        out.append({"x": (b[0] + b[2]) / 2 / plot_w, "y": (b[1] + b[3]) / 2 / plot_h, "xref": "paper",
                    "yref": "paper", "xanchor": "center", "yanchor": "middle", "text": html.escape(text),
                    "showarrow": False, "font": {"color": "#aa3333", "size": LABEL_PX, "family": FONT},
                    "name": "limit"})
    return out


def chart_figure(chart: Chart) -> dict:
    """The Plotly figure (``{"data", "layout"}``) of one chart."""
    axes = chart_axes(chart)
    legend_h = 26 * _legend_rows(chart)
    margin = dict(MARGIN, b=58 + legend_h)
    height = HEIGHT + legend_h
    plot_w, plot_h = WIDTH - margin["l"] - margin["r"], height - margin["t"] - margin["b"]
    seconds = chart.time_axis
    layout = {"width": WIDTH, "height": height, "margin": margin, "font": {"family": FONT, "size": 12},
              "hovermode": "closest", "plot_bgcolor": "white",
              "xaxis": {"type": "log", "range": [axes.x_lo, axes.x_hi], "title": {"text": html.escape(chart.x_label)},
                        "gridcolor": "#e5e5e5", "linecolor": "#444", "mirror": True, "zeroline": False,
                        **_ticks(axes.x_lo, axes.x_hi, seconds)},
              "yaxis": {"type": "log", "range": [axes.y_lo, axes.y_hi], "title": {"text": html.escape(chart.y_label)},
                        "gridcolor": "#e5e5e5", "linecolor": "#444", "mirror": True, "zeroline": False,
                        **_ticks(axes.y_lo, axes.y_hi, False)},
              "legend": {"orientation": "h", "x": 0.0, "xanchor": "left", "y": -58.0 / plot_h, "yanchor": "top"},
              "annotations": _annotations(chart, axes, plot_w, plot_h)}
    return {"data": _traces(chart, axes), "layout": layout}


def _table_html(t: Table) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in t.header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in t.rows)
    return (f'<div class="table" data-stages="{" ".join(t.stages)}"><h3>{html.escape(t.title)}</h3>'
            f'<p class="why">{html.escape(t.why)}</p><table><thead><tr>{head}</tr></thead>'
            f"<tbody>{body}</tbody></table></div>")


def _points_table(chart: Chart) -> str:
    keys = list(dict.fromkeys(k for p in chart.points for k in p.hover))
    head = "".join(f"<th>{html.escape(k)}</th>" for k in keys)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(p.hover.get(k, ''))}</td>" for k in keys) + "</tr>"
                   for p in chart.points)
    return (f"<details><summary>the figures ({len(chart.points)} settings)</summary><div class=\"scroll\"><table>"
            f"<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></div></details>")


def chart_html(c: Chart) -> str:
    """A chart's ``<figure>``: question, plot element, sentence, note, its figures folded away."""
    note = f'<p class="note">{html.escape(c.note)}</p>' if c.note else ""
    return (f'<figure class="chart" data-stages="{" ".join(c.stages)}" id="fig-{c.key}">'
            f"<h3>{html.escape(c.title)}</h3><div class=\"plot\" id=\"chart-{c.key}\"></div>"
            f'<p class="rec">{html.escape(c.sentence)}</p>{note}{_points_table(c)}</figure>')


def _body(charts: Sequence[Chart], tables: Sequence[Table], title: str, intro: str) -> str:
    stages = sorted({s for c in charts for s in c.stages} | {s for t in tables for s in t.stages})
    options = "".join(f'<option value="{html.escape(s)}">{html.escape(s)}</option>' for s in stages)
    groups: dict[str, list[Chart]] = {}
    for c in charts:
        groups.setdefault(c.group or "Charts", []).append(c)
    parts = [f"<h1>{html.escape(title)}</h1>", intro,
             f'<p class="controls"><label for="stage">Stage: </label><select id="stage">'
             f'<option value="">every stage</option>{options}</select> <span id="shown"></span></p>']
    nav = " · ".join(f'<a href="#g-{i}">{html.escape(g)}</a>' for i, g in enumerate(groups))
    tables_link = ' · <a href="#tables">tables</a>' if tables else ""
    parts.append(f"<nav>{nav}{tables_link}</nav>")
    for i, (g, cs) in enumerate(groups.items()):
        st = " ".join(sorted({s for c in cs for s in c.stages}))
        parts.append(f'<section class="group" data-stages="{st}" id="g-{i}"><h2>{html.escape(g)}</h2>'
                     + "".join(chart_html(c) for c in cs) + "</section>")
    if tables:
        st = " ".join(sorted({s for t in tables for s in t.stages}))
        parts.append(f'<section class="group" id="tables" data-stages="{st}"><h2>Figures without a chart</h2>'
                     + "".join(_table_html(t) for t in tables) + "</section>")
    return "\n".join(parts)


def library_tag(path: Path, js: str) -> str:
    """The ``<script>`` of the chart library for a page at ``path``: ``js="inline"`` embeds it,
    ``"beside"`` writes ``plotly-<version>.min.js`` next to the page (once) and links it."""
    import plotly
    from plotly.offline import get_plotlyjs

    if js == "inline":
        return f"<script>{get_plotlyjs()}</script>"
    name = f"plotly-{plotly.__version__}.min.js"
    target = path.parent / name
    text = get_plotlyjs()
    if not target.is_file() or target.stat().st_size != len(text.encode("utf-8")):
        target.write_text(text, encoding="utf-8")
    return f'<script src="{name}"></script>'


def write_page(path: str | Path, charts: Sequence[Chart], tables: Sequence[Table] = (), *, title: str,
               intro: str = "", js: str = "beside") -> Path:
    """Write the page to ``path``; ``intro`` is trusted HTML (the caller escapes its parts).

    ``js="beside"`` writes ``plotly-<version>.min.js`` next to the page (once), ``"inline"``
    embeds it.
    """
    if js not in ("beside", "inline"):
        raise ValueError(f"write_page: js must be 'beside' or 'inline', got {js!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    page = _PAGE.format(title=html.escape(title), body=_body(charts, tables, title, intro),
                        plotly=library_tag(path, js), script=render_script(charts) + _SELECTOR)
    path.write_text(page, encoding="utf-8")
    return path


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,">
<style>
body {{ font-family: Liberation Sans, Arial, Helvetica, sans-serif; margin: 1.5em auto; max-width: 900px;
       color: #222; padding: 0 12px; }}
h2 {{ border-bottom: 1px solid #ccc; padding-bottom: 4px; margin-top: 2em; }}
h3 {{ margin: 1.2em 0 0.3em 0; }}
figure {{ margin: 0 0 1.5em 0; }}
.rec {{ font-size: 15px; background: #f4f7fb; border-left: 4px solid #1f77b4; padding: 6px 10px; }}
.note, .why {{ font-size: 13px; color: #555; }}
nav {{ font-size: 14px; margin-bottom: 1em; }}
table {{ border-collapse: collapse; font-size: 12px; margin: 0.5em 0; }}
th, td {{ border: 1px solid #ddd; padding: 3px 6px; text-align: left; vertical-align: top; }}
th {{ background: #f3f3f3; }}
.scroll {{ overflow-x: auto; }}
.hidden {{ display: none; }}
.glance li {{ margin-bottom: 0.4em; }}
</style>
{plotly}
</head><body>
{body}
{script}
</body></html>
"""

_RENDER = """<script>
const FIGURES = %s;
const CONFIG = {displaylogo: false, responsive: false, toImageButtonOptions: {format: "png", scale: 2}};
const drawn = Object.entries(FIGURES).map(([id, fig]) => Plotly.newPlot(id, fig.data, fig.layout, CONFIG));
Promise.all(drawn).then(() => { document.body.dataset.rendered = String(drawn.length); });
</script>
"""

_SELECTOR = """<script>
function showStage(stage) {
  let n = 0;
  document.querySelectorAll("[data-stages]").forEach(el => {
    const on = !stage || el.dataset.stages.split(" ").includes(stage);
    el.classList.toggle("hidden", !on);
    if (on && el.tagName === "FIGURE") n += 1;
  });
  document.getElementById("shown").textContent = n + " chart" + (n === 1 ? "" : "s") + " shown";
}
document.getElementById("stage").addEventListener("change", e => showStage(e.target.value));
showStage("");
</script>
"""


def render_script(charts: Sequence[Chart]) -> str:
    """The ``<script>`` that draws ``charts`` into their :func:`chart_html` elements and sets
    ``data-rendered`` on ``<body>`` when all are drawn."""
    figures = {f"chart-{c.key}": chart_figure(c) for c in charts}
    return _RENDER % json.dumps(figures, separators=(",", ":")).replace("</", "<\\/")
