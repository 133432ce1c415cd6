"""The charts as matplotlib figures: one chart, or a summary grid of a few, sized in pixels.

Every panel is laid out by hand in pixels (title, plot area, tick labels, legend, the
recommendation sentence), so the plot area's size is known before the labels are placed
(:func:`pipeline.charts.labels.place_labels`) and the figure is legible at the width it is
made for (``width_px``; the summary defaults to 900 px, what GitHub shows a README image at).

Examples
--------
>>> import tempfile, os
>>> from pipeline.charts.model import Chart, Point
>>> c = Chart("k", "Which?", "seconds", "error", [Point(0.01, 1.0, "fast", "a"), Point(0.1, 0.1, "slow", "a", True)],
...           sentence="Pick slow.")
>>> path = os.path.join(tempfile.mkdtemp(), "c.png")
>>> summary_figure([c], path, cols=1, width_px=500)["panels"]
1
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from pipeline.charts.labels import chart_placement, limit_boxes, text_size
from pipeline.charts.model import (
    MARKERS,
    Chart,
    chart_axes,
    chart_fronts,
    log_ticks,
    plot_value,
    point_label,
    tick_labels,
)

__all__ = ["summary_figure", "chart_png", "PanelStyle"]

DPI = 100


@dataclass
class PanelStyle:
    """Sizes of one panel, px (at :data:`DPI`)."""

    width: float = 450.0
    plot_height: float = 260.0
    left: float = 62.0
    right: float = 14.0
    title_px: float = 12.5
    label_px: float = 10.5
    tick_px: float = 10.0
    text_px: float = 10.5


def _pt(px: float) -> float:
    return px * 72.0 / DPI


def _wrap(text: str, width_px: float, font_px: float, char_em: float = 0.56) -> list[str]:
    chars = max(10, int(width_px / (char_em * font_px)))
    return textwrap.wrap(text, chars) if text else []


def _legend_entries(chart: Chart) -> list[str]:
    names = [s for s in chart.series_names() if s]
    extra = ["Pareto front"] if chart_fronts(chart) else []
    return names + extra + (["shipped default"] if any(p.default for p in chart.points) else [])


def _legend_rows(entries: list[str], width: float, font_px: float) -> int:
    rows, used = (1 if entries else 0), 0.0
    for e in entries:
        w = text_size(e, font_px)[0] + 30.0
        if used + w > width and used > 0:
            rows, used = rows + 1, 0.0
        used += w
    return rows


def _panel_heights(chart: Chart, st: PanelStyle) -> dict:
    inner = st.width - st.left - st.right
    title = _wrap(chart.title, st.width - 8, st.title_px, 0.66)
    text = _wrap(chart.sentence + (" " + chart.note if chart.note else ""), st.width - 8, st.text_px)
    legend = _legend_rows(_legend_entries(chart), inner, st.label_px)
    return {"title": title, "text": text, "legend": legend,
            "top": 8 + len(title) * st.title_px * 1.3 + 6, "axis": 44.0,
            "legend_h": legend * st.label_px * 1.7 + (6 if legend else 0),
            "text_h": len(text) * st.text_px * 1.3 + 10}


def _draw_axes(ax, chart: Chart, st: PanelStyle, plot_w: float, plot_h: float) -> None:
    axes = chart_axes(chart)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(10 ** axes.x_lo, 10 ** axes.x_hi)
    ax.set_ylim(10 ** axes.y_lo, 10 ** axes.y_hi)
    xt = log_ticks(axes.x_lo, axes.x_hi)
    ax.set_xticks(xt, tick_labels(xt, chart.time_axis), fontsize=_pt(st.tick_px))
    yt = log_ticks(axes.y_lo, axes.y_hi)
    ax.set_yticks(yt, tick_labels(yt, False), fontsize=_pt(st.tick_px))
    ax.minorticks_off()
    ax.grid(True, which="major", alpha=0.25)
    ax.set_xlabel(chart.x_label, fontsize=_pt(st.label_px), labelpad=2)
    ax.set_ylabel(chart.y_label, fontsize=_pt(st.label_px), labelpad=2)
    styles = {s: MARKERS[i % len(MARKERS)] for i, s in enumerate(chart.series_names())}
    for front in chart_fronts(chart):
        fp = [chart.points[i] for i in front]
        if len(fp) > 1:
            colour = "#555555" if chart.front == "all" else styles[fp[0].series][0]
            ax.step([plot_value(p.x, axes.x_floor) for p in fp], [plot_value(p.y, axes.y_floor) for p in fp],
                    where="post", color=colour, lw=1.1, ls="--", alpha=0.8, zorder=1)
    for s, (colour, marker, _) in styles.items():
        pts = [p for p in chart.points if p.series == s]
        if chart.connect and len(pts) > 1:
            ax.plot([plot_value(p.x, axes.x_floor) for p in pts], [plot_value(p.y, axes.y_floor) for p in pts],
                    color=colour, lw=0.8, alpha=0.45, zorder=2)
        ax.scatter([plot_value(p.x, axes.x_floor) for p in pts], [plot_value(p.y, axes.y_floor) for p in pts],
                   s=36, color=colour, marker=marker, zorder=3, label=s or None, edgecolors="white", linewidths=0.5)
    dflt = [p for p in chart.points if p.default]
    if dflt:
        ax.scatter([plot_value(p.x, axes.x_floor) for p in dflt], [plot_value(p.y, axes.y_floor) for p in dflt],
                   s=190, facecolors="none", edgecolors="black", linewidths=1.4, zorder=4)
    boxes = limit_boxes(chart, axes, plot_w, plot_h, st.label_px)
    for key, limit, line in (("budget", chart.budget, ax.axvline), ("target", chart.target, ax.axhline)):
        if limit:
            line(limit[0], color="#aa3333", lw=1.0, ls=":", zorder=0)
            b = boxes[key]
            ax.text((b[0] + b[2]) / 2 / plot_w, (b[1] + b[3]) / 2 / plot_h, limit[1], transform=ax.transAxes,
                    ha="center", va="center", fontsize=_pt(st.label_px), color="#aa3333")
    _draw_labels(ax, chart, axes, st, plot_w, plot_h)


def _draw_labels(ax, chart, axes, st, plot_w, plot_h) -> None:
    texts = [point_label(p) for p in chart.points]
    pl = chart_placement(chart, plot_w, plot_h, st.label_px)
    for p, t, off, lead in zip(chart.points, texts, pl.offsets, pl.leaders):
        ax.annotate(t, (plot_value(p.x, axes.x_floor), plot_value(p.y, axes.y_floor)),
                    xytext=(_pt(off[0]), _pt(off[1])), textcoords="offset points", ha="center", va="center",
                    fontsize=_pt(st.label_px), zorder=5,
                    arrowprops={"arrowstyle": "-", "color": "#888888", "lw": 0.6, "shrinkA": 0, "shrinkB": 4}
                    if lead else None)


def _draw_panel(fig, chart: Chart, st: PanelStyle, x0: float, y_top: float, fig_w: float, fig_h: float) -> float:
    """Draw one panel whose top-left corner is (x0, y_top) px (y down); return its height."""
    h = _panel_heights(chart, st)
    y = y_top + 8
    for line in h["title"]:
        fig.text((x0 + 4) / fig_w, 1 - (y + st.title_px) / fig_h, line, fontsize=_pt(st.title_px), weight="bold")
        y += st.title_px * 1.3
    y = y_top + h["top"]
    plot_w = st.width - st.left - st.right
    ax = fig.add_axes(((x0 + st.left) / fig_w, 1 - (y + st.plot_height) / fig_h, plot_w / fig_w,
                       st.plot_height / fig_h))
    _draw_axes(ax, chart, st, plot_w, st.plot_height)
    y += st.plot_height + h["axis"]
    entries = _legend_entries(chart)
    if entries:
        handles, names = ax.get_legend_handles_labels()
        handles = list(handles)
        from matplotlib.lines import Line2D

        if chart_fronts(chart):
            handles.append(Line2D([], [], color="#555555", ls="--", lw=1.1))
            names.append("Pareto front")
        if any(p.default for p in chart.points):
            handles.append(Line2D([], [], marker="o", ls="", markerfacecolor="none", markeredgecolor="black",
                                  markersize=11))
            names.append("shipped default")
        ncol = max(1, math.ceil(len(names) / max(1, h["legend"])))
        fig.legend(handles, names, loc="upper left", bbox_to_anchor=((x0 + st.left - 8) / fig_w, 1 - y / fig_h),
                   ncol=ncol, fontsize=_pt(st.label_px), frameon=False, handletextpad=0.3, columnspacing=1.0,
                   borderaxespad=0.0, borderpad=0.0)
        y += h["legend_h"]
    for line in h["text"]:
        fig.text((x0 + 4) / fig_w, 1 - (y + st.text_px) / fig_h, line, fontsize=_pt(st.text_px))
        y += st.text_px * 1.3
    return y + 10 - y_top


def _panel_height(chart: Chart, st: PanelStyle) -> float:
    h = _panel_heights(chart, st)
    return (h["top"] + st.plot_height + h["axis"] + h["legend_h"]
            + h["text_h"] + 18)


def summary_figure(charts: Sequence[Chart], path: str | Path, *, cols: int = 2, width_px: float = 900.0,
                   title: str | None = None, footer: str | None = None) -> dict:
    """Write ``charts`` (at most 6 are asked for, not enforced) as one PNG of ``cols`` columns,
    ``width_px`` wide; returns ``{"path", "panels", "size": (w, h)}``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    charts = list(charts)
    st = PanelStyle(width=width_px / cols)
    rows = [charts[i:i + cols] for i in range(0, len(charts), cols)] or [[]]
    heights = [max([_panel_height(c, st) for c in r] or [40.0]) for r in rows]
    head = 34.0 if title else 0.0
    foot = 22.0 if footer else 0.0
    fig_w, fig_h = width_px, head + sum(heights) + foot
    fig = plt.figure(figsize=(fig_w / DPI, fig_h / DPI), dpi=DPI)
    if title:
        fig.text(0.01, 1 - 24 / fig_h, title, fontsize=_pt(15), weight="bold")
    y = head
    for r, h in zip(rows, heights):
        for j, c in enumerate(r):
            _draw_panel(fig, c, st, j * st.width, y, fig_w, fig_h)
        y += h
    if footer:
        fig.text(0.01, 6 / fig_h, footer, fontsize=_pt(9.5), color="#555555")
    from sim.figures import save_figure

    save_figure(fig, path, dpi=DPI, tight=False)
    return {"path": str(path), "panels": len(charts), "size": (int(fig_w), int(round(fig_h)))}


def chart_png(chart: Chart, path: str | Path, *, width_px: float = 700.0) -> dict:
    """One chart as a PNG ``width_px`` wide."""
    return summary_figure([chart], path, cols=1, width_px=width_px)
