"""``iristac bench report RESULTS.json --out page.html``: the charts of a saved benchmark run.

From the JSON that ``iristac bench all`` writes (or one benchmark's ``--json``), all from the
same rows (:mod:`pipeline.charts.decisions`):

- an offline interactive page (``--out``): one chart per decision, hover for the exact
  figures and the machine, a stage selector; the figures no chart shows as tables;
- a summary figure (``--figure``): at most six panels, 900 px wide (README, docs);
- with ``--charts DIR``: one PNG per decision chart (what ``docs/benchmarks.md`` shows).

Python: :func:`build_report`, :func:`markdown_charts`.
"""

from __future__ import annotations

import html
from pathlib import Path

from pipeline.charts.decisions import Overview, overview, summary_charts
from pipeline.charts.model import Table, format_seconds, format_value
from pipeline.charts.rows import load_results, result_rows
from pipeline.results.report import format_number

__all__ = ["add_arguments", "run", "format_table", "build_report", "markdown_charts", "chart_tables", "write_docs",
           "format_markdown", "CHART_DIR"]


def add_arguments(parser) -> None:
    parser.add_argument("results", metavar="RESULTS.json", help="a saved run: iristac bench all's JSON")
    parser.add_argument("--out", default="benchmarks.html", help="the page to write (default benchmarks.html)")
    parser.add_argument("--figure", default=None, metavar="PNG", help="also write the summary figure here")
    parser.add_argument("--charts", default=None, metavar="DIR", help="also write one PNG per decision chart here")
    parser.add_argument("--markdown", default=None, metavar="MD",
                        help="write the docs as bench all does instead: MD, its .html page beside it, the chart "
                             "PNGs in images/benchmarks/ and --figure (redraws docs/ from a saved run)")
    parser.add_argument("--inline-js", action="store_true",
                        help="embed the chart library in the page (one file to send, +4.8 MB) instead of "
                             "writing plotly-VERSION.min.js beside it")


def chart_tables(ov: Overview) -> list[Table]:
    """The overview's un-charted figures as page tables."""
    out = []
    for t in ov.tables:
        header = ["setting", "error", "time", "machine"]
        rows = [[str(r["setting"]),
                 "–" if r.get("error") is None else f"{format_value(r['error'])} {r.get('error_unit') or ''}".strip(),
                 format_seconds(r.get("seconds")), str(r.get("machine", ""))] for r in t["rows"]]
        out.append(Table(f"{t['bench']}: {t['knob']}", t["why"], header, rows, (str(t["bench"]),)))
    return out


def _intro(results: dict, source: str, ov: Overview) -> str:
    machines = "; ".join(html.escape(m) for m in ov.machines) or "unknown"
    quick = " (a --quick run: smaller sizes, for a smoke test)" if results.get("quick") else ""
    load = results.get("load_average") or []
    load_txt = (f" Load average (1 min) {load[0]:.2f} at the start, {load[3]:.2f} at the end." if len(load) >= 4
                else "")
    glance = "".join(f'<li><a href="#fig-{c.key}">{html.escape(c.title)}</a> {html.escape(c.sentence)}</li>'
                     for c in summary_charts(ov.charts))
    glance = f"<h2>At a glance</h2><ul class=\"glance\">{glance}</ul>" if glance else ""
    return (f"<p>Error against time for every decision the benchmarks measure{quick}: log axes, the Pareto front "
            f"dashed (no setting is both faster and more accurate than a point on it), the shipped default ringed, "
            f"and under each chart what to pick, computed from the figures. Hover a point for its exact figures and "
            f"the machine.</p><p class=\"note\">Source: {html.escape(source)}. Machine: {machines}.{load_txt}</p>"
            + glance)


def build_report(results: dict | str | Path, out: str | Path, *, figure: str | Path | None = None,
                 charts_dir: str | Path | None = None, js: str = "beside", source: str | None = None,
                 ov: Overview | None = None) -> dict:
    """Write the page (and the summary figure, the chart PNGs) of a benchmark run.

    ``results`` is a run (dict) or the path of its JSON; ``ov`` its charts when the caller has
    built them already. Returns what was written and the charts' keys, titles and sentences.
    """
    from pipeline.charts.page import write_page

    if not isinstance(results, dict):
        source = source or str(results)
        results = load_results(results)
    ov = ov if ov is not None else overview(result_rows(results))
    page = write_page(out, ov.charts, chart_tables(ov), title="IrisTac benchmarks: what accuracy costs in time",
                      intro=_intro(results, source or "iristac bench all", ov), js=js)
    written = {"page": str(page), "charts": [{"key": c.key, "title": c.title, "sentence": c.sentence,
                                              "points": len(c.points)} for c in ov.charts],
               "tables": len(ov.tables)}
    if figure:
        written["figure"] = write_summary(ov, figure)["path"]
    if charts_dir:
        written["chart_pngs"] = write_chart_pngs(ov, charts_dir)
    return written


def write_summary(ov: Overview, path: str | Path) -> dict:
    """The summary figure: the :data:`pipeline.charts.decisions.SUMMARY` charts, 2 columns, 900 px."""
    from pipeline.charts.static import summary_figure

    charts = summary_charts(ov.charts)
    machine = ov.machines[0] if len(ov.machines) == 1 else f"{len(ov.machines)} machines"
    return summary_figure(charts, path, cols=2, width_px=900,
                          title="What accuracy costs in time (iristac bench all)",
                          footer=f"Measured on {machine}. Dashed: Pareto front; ringed: shipped default; "
                                 f"full page: docs/benchmarks.html")


def _decision_charts(ov: Overview):
    return [c for c in ov.charts if not c.group.startswith("Other")]


def write_chart_pngs(ov: Overview, folder: str | Path) -> list[str]:
    """One PNG per decision chart (not the "other measurements" ones) into ``folder``."""
    from pipeline.charts.static import chart_png

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return [chart_png(c, folder / f"{c.key}.png")["path"] for c in _decision_charts(ov)]


def markdown_charts(results: dict, image_prefix: str | None, ov: Overview | None = None) -> list[str]:
    """Markdown lines: per decision, its question, its chart (``image_prefix/KEY.png``) and sentence
    (``ov``: the run's charts, when already built)."""
    ov = ov if ov is not None else overview(result_rows(results))
    lines: list[str] = []
    group = None
    for c in _decision_charts(ov):
        if c.group != group:
            group = c.group
            lines += [f"### {group}", ""]
        lines += [f"**{c.title}**", ""]
        if image_prefix is not None:
            lines += [f"![{c.title}]({image_prefix}/{c.key}.png)", ""]
        lines += [f"> {c.sentence}", ""]
        if c.note:
            lines += [f"_{c.note}_", ""]
    return lines


def run(args) -> dict:
    if getattr(args, "markdown", None):
        out = load_results(args.results)
        write_docs(out, Path(args.markdown), args.figure)
        return {"page": out["page"], "figure": out.get("plot"), "charts": [], "tables": 0,
                "markdown": out["markdown"]}
    return build_report(args.results, args.out, figure=args.figure, charts_dir=args.charts,
                        js="inline" if getattr(args, "inline_js", False) else "beside")


def format_table(result: dict) -> str:
    lines = [f"wrote {result['page']} ({len(result['charts'])} charts, {result['tables']} tables)"]
    if result.get("markdown"):
        lines = [f"wrote {result['markdown']} and {result['page']}"]
    if result.get("figure"):
        lines.append(f"wrote {result['figure']}")
    if result.get("chart_pngs"):
        lines.append(f"wrote {len(result['chart_pngs'])} chart PNGs")
    lines += [f"- {c['title']}: {c['sentence']}" for c in result["charts"]]
    return "\n".join(lines)


#: Where the per-decision chart PNGs go, relative to the markdown file.
CHART_DIR = "images/benchmarks"


def write_docs(out: dict, md_path: Path, plot: str | None) -> None:
    """The page, the summary figure, the chart PNGs and the markdown of a run (``out``, as
    ``benchmarks.json`` holds it) beside ``md_path``; fills in what was written."""
    raw = md_path.with_suffix(".json")
    ov = overview(result_rows(out))  # once, for the page, the figures and the markdown
    written = build_report(dict(out), md_path.with_suffix(".html"), figure=plot,
                           charts_dir=md_path.parent / CHART_DIR, source=f"iristac bench all ({raw.name})", ov=ov)
    md = format_markdown(out, plot_name=_relative(plot, md_path.parent) if plot else None, chart_prefix=CHART_DIR,
                         page_name=md_path.with_suffix(".html").name, ov=ov)
    md_path.write_text(md, encoding="utf-8")
    out.update(markdown=str(md_path), page=written["page"], json=str(raw))
    if plot:
        out["plot"] = str(plot)


def _relative(path: str, folder: Path) -> str:
    p = Path(path).resolve()
    try:
        return str(p.relative_to(folder.resolve()))
    except ValueError:
        return str(path)


def format_markdown(result: dict, plot_name: str | None = None, chart_prefix: str | None = None,
                    page_name: str | None = None, ov: Overview | None = None) -> str:
    """The run as markdown: the summary figure, one chart and sentence per decision (when
    ``chart_prefix`` names their folder), then every row in a table per benchmark."""
    load = result.get("load_average")
    lines = ["# Benchmarks", "",
             "Written by `iristac bench all`" + (" --quick" if result.get("quick") else "") + ". "
             "Every figure below was measured by that command on the machine named in its row; "
             "error and time sit side by side so that what accuracy costs in time is visible.", "",
             f"Machine: {result['machine']}" + (f"; load average {load[0]:.2f} at the start, {load[3]:.2f} at the end"
                                                if load else ""), ""]
    if plot_name:
        lines += [f"![what accuracy costs in time: six decisions]({plot_name})", ""]
    if page_name:
        lines += [f"Every chart, interactive (hover for the exact figures and the machine, filter by stage): "
                  f"[{page_name}]({page_name}), offline (open it from a clone). `iristac bench report RUN.json` "
                  f"draws the same page from any saved run; `iristac bench compare OLD.json NEW.json` lists the rows "
                  f"that got slower or less accurate beyond the noise.", ""]
    if chart_prefix is not None:
        lines += ["## What to pick", "", "Each chart: error against time on log axes, the Pareto front dashed, the "
                  "shipped default ringed; the sentence under it is computed from the figures.", ""]
        lines += markdown_charts(result, chart_prefix, ov)
    lines += ["## Every row", ""]
    for s in result["sections"]:
        lines += [f"### {s['bench']}", "", f"(benchmark ran for {s['seconds']:.1f} s)", ""]
        if s["error"]:
            lines += [f"**failed**: `{s['error']}`", ""]
            continue
        if s["rows"]:
            lines += ["| knob | setting | error | seconds | machine |", "|---|---|---|---|---|"]
            for r in s["rows"]:
                err = format_number(r.get("error"))
                if r.get("error") is not None and r.get("error_unit"):
                    err += f" {r['error_unit']}"
                lines.append(f"| {r['knob']} | {r['setting']} | {err} | {format_number(r.get('seconds'))} | "
                             f"{r['machine']} |")
            lines.append("")
        if s["table"]:
            lines += ["```", s["table"].rstrip(), "```", ""]
    return "\n".join(lines)
