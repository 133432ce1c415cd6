"""What a chart shows: points (time, error), series, the Pareto front, the default, the axes.

Both axes are logarithmic. A time or an error of exactly zero (a reference measured against
itself, a step that costs nothing) cannot sit on a log axis: it is drawn on the axis's floor,
a tenth of the smallest positive value, and its label says ``= 0``.

Examples
--------
>>> pts = [Point(0.01, 1.0, "a"), Point(0.1, 0.1, "b"), Point(0.2, 0.5, "c")]
>>> front_indices(pts)
[0, 1]
>>> format_seconds(0.0036), format_seconds(2.5), format_value(0.012345)
('3.6 ms', '2.5 s', '0.01235')
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

__all__ = ["Point", "Chart", "Table", "Axes", "chart_axes", "point_label", "front_indices", "chart_fronts", "log_range",
           "format_seconds", "format_value",
           "log_ticks", "tick_labels", "plot_value", "MARKERS"]

#: Series styles, the same in both renderers: (colour, matplotlib marker, Plotly symbol).
MARKERS = [("#1f77b4", "o", "circle"), ("#d62728", "s", "square"), ("#2ca02c", "D", "diamond"),
           ("#9467bd", "^", "triangle-up"), ("#ff7f0e", "v", "triangle-down"), ("#8c564b", "P", "cross"),
           ("#e377c2", "X", "x"), ("#7f7f7f", "p", "pentagon"), ("#bcbd22", "h", "hexagon"),
           ("#17becf", "*", "star")]


@dataclass
class Point:
    """One measured setting: ``x`` seconds (or another cost), ``y`` error, a short label.

    ``hover`` holds the exact figures (name -> text) the interactive page shows on hover;
    ``name`` how a sentence names the point (default: series and label); ``x_noise`` the
    relative spread of ``x``'s timed repeats (:func:`pipeline.charts.rows.time_noise`; None:
    not recorded), so a sentence does not call a point faster within the timing noise.
    """

    x: float
    y: float
    label: str
    series: str = ""
    default: bool = False
    hover: dict[str, str] = field(default_factory=dict)
    name: str = ""
    x_noise: float | None = None

    def title(self) -> str:
        """How a sentence names the point: ``name``, else series and label."""
        return self.name or (f"{self.series} {self.label}".strip() if self.series else self.label)


@dataclass
class Chart:
    """One question answered by one chart.

    ``front`` is ``"all"`` (the points are alternatives for one job: one front) or
    ``"series"`` (each series is its own job, e.g. eager against fast per solver: a front per
    series). ``budget`` (x, text) and ``target`` (y, text) draw a limit line each;
    ``connect`` joins each series' points in their order (a curve, e.g. rays growing).
    """

    key: str
    title: str
    x_label: str
    y_label: str
    points: list[Point]
    sentence: str = ""
    note: str = ""
    front: str = "all"
    budget: tuple[float, str] | None = None
    target: tuple[float, str] | None = None
    stages: tuple[str, ...] = ()
    group: str = ""
    connect: bool = False

    @property
    def time_axis(self) -> bool:
        """Whether ``x`` is a time in seconds (its ticks then read "10 ms", "1 s")."""
        return "second" in self.x_label or self.x_label.endswith("(s)")

    def series_names(self) -> list[str]:
        """Series in order of first appearance."""
        return list(dict.fromkeys(p.series for p in self.points))


def front_indices(points: Sequence[Point]) -> list[int]:
    """Indices of the Pareto-optimal points (no other point is at most as slow and as wrong and
    better in one), sorted by time.

    Examples
    --------
    >>> front_indices([Point(1, 1, "a"), Point(1, 1, "twin"), Point(2, 2, "worse")])
    [0, 1]
    """
    idx = []
    for i, p in enumerate(points):
        dominated = any((q.x <= p.x and q.y <= p.y) and (q.x < p.x or q.y < p.y) for q in points)
        if not dominated:
            idx.append(i)
    return sorted(idx, key=lambda i: (points[i].x, points[i].y))


def chart_fronts(chart: Chart) -> list[list[int]]:
    """The chart's front(s) as lists of point indices: one, or one per series."""
    if chart.front == "none":
        return []
    if chart.front == "series":
        out = []
        for s in chart.series_names():
            members = [i for i, p in enumerate(chart.points) if p.series == s]
            if len(members) > 1:
                out.append([members[j] for j in front_indices([chart.points[i] for i in members])])
        return out
    return [front_indices(chart.points)]


def log_range(values: Sequence[float], pad: float = 0.12) -> tuple[float, float, float]:
    """``(lo, hi, floor)``: a log10 axis range over the positive ``values``, padded by ``pad``
    of its span (at least 0.3 decade in all), and the value that zeros are drawn at.

    Examples
    --------
    >>> lo, hi, floor = log_range([0.0, 0.01, 1.0])
    >>> round(lo, 2), round(hi, 2), floor
    (-3.36, 0.36, 0.001)
    """
    pos = [v for v in values if v is not None and v > 0 and math.isfinite(v)]
    if not pos:
        return -1.0, 1.0, 0.1
    lo, hi = math.log10(min(pos)), math.log10(max(pos))
    floor = 10 ** (lo - 1.0)
    if any(v is not None and v <= 0 for v in values):
        lo = lo - 1.0
    span = max(hi - lo, 0.3)
    mid = (hi + lo) / 2
    lo, hi = mid - span / 2, mid + span / 2
    return lo - pad * span, hi + pad * span, floor


def tick_labels(values, seconds: bool) -> list[str]:
    """Tick texts, the same in both renderers: times as :func:`format_seconds`, others as numbers."""
    return [format_seconds(v) if seconds else format_value(v, 3) for v in values]


def log_ticks(lo: float, hi: float) -> list[float]:
    """Tick values on a log axis from 10**lo to 10**hi: decades, or 1-2-5 steps on a short axis."""
    span = hi - lo
    subs = ((1.0,) if span > 2.5 else (1.0, 3.0) if span > 1.2 else (1.0, 2.0, 5.0) if span > 0.6
            else tuple(float(k) for k in range(1, 10)))
    out = []
    for e in range(math.floor(lo) - 1, math.ceil(hi) + 1):
        out += [s * 10.0 ** e for s in subs if lo <= math.log10(s * 10.0 ** e) <= hi]
    return out


def plot_value(v: float, floor: float) -> float:
    """``v``, or ``floor`` where it cannot sit on a log axis (zero or negative)."""
    return v if v > 0 else floor


def format_seconds(s: float | None) -> str:
    """Seconds in the unit a person reads best (us, ms, s, min), 2-3 significant digits.

    Examples
    --------
    >>> format_seconds(4.2e-5), format_seconds(0.0123), format_seconds(95.0), format_seconds(0.0)
    ('42 us', '12.3 ms', '1.58 min', '0 s')
    """
    if s is None or not math.isfinite(s):
        return "–"
    if s == 0:
        return "0 s"
    for scale, unit in ((60.0, "min"), (1.0, "s"), (1e-3, "ms"), (1e-6, "us")):
        if abs(s) >= scale or unit == "us":
            v = s / scale
            if unit == "min" and abs(s) < 90:
                continue
            return f"{v:.3g} {unit}"
    return f"{s:g} s"


def format_value(v: float | None, digits: int = 4) -> str:
    """A number to ``digits`` significant digits (``–`` for none)."""
    if v is None or not math.isfinite(v):
        return "–"
    return f"{v:.{digits}g}"


@dataclass
class Axes:
    """Log10 ranges of both axes and the values zeros are drawn at."""

    x_lo: float
    x_hi: float
    x_floor: float
    y_lo: float
    y_hi: float
    y_floor: float

    def to_px(self, x: float, y: float, width: float, height: float) -> tuple[float, float]:
        """A point's position in a ``width`` x ``height`` px plot area (origin lower left)."""
        u = (math.log10(plot_value(x, self.x_floor)) - self.x_lo) / (self.x_hi - self.x_lo)
        v = (math.log10(plot_value(y, self.y_floor)) - self.y_lo) / (self.y_hi - self.y_lo)
        return u * width, v * height


def chart_axes(chart: Chart) -> Axes:
    """The axes of ``chart``: every point, the budget and the target inside, padded."""
    xs = [p.x for p in chart.points] + ([chart.budget[0]] if chart.budget else [])
    ys = [p.y for p in chart.points] + ([chart.target[0]] if chart.target else [])
    x_lo, x_hi, x_floor = log_range(xs)
    y_lo, y_hi, y_floor = log_range(ys)
    return Axes(x_lo, x_hi, x_floor, y_lo, y_hi, y_floor)


def point_label(p: Point) -> str:
    """The label drawn beside a point (``= 0`` where a zero sits on the axis floor)."""
    zero = [name for name, v in (("time", p.x), ("error", p.y)) if v <= 0]
    return p.label + (f" ({' and '.join(zero)} = 0)" if zero else "")


@dataclass
class Table:
    """Figures no chart shows (a single setting, a time without an error), with why."""

    title: str
    why: str
    header: list[str]
    rows: list[list[str]]
    stages: tuple[str, ...] = ()
