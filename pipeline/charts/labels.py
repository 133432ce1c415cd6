"""Point labels that overlap neither each other nor the points, in a plot area of known size.

Both renderers (matplotlib and Plotly) place labels with :func:`place_labels`, so the page
and the PNG agree. (adjustText does this for matplotlib alone, from its artists; the page
needs the same placement without matplotlib.) The placement is greedy: the most crowded
point first, each label at the first of a list of candidate positions around its point,
nearest first, that keeps the label inside the plot and clear of every placed label and
every marker; a label moved away from its point gets a leader line. Where no candidate is
clear (more text than room), the least-overlapping one is taken and reported.

Examples
--------
>>> import numpy as np
>>> pl = place_labels(np.array([[100.0, 100.0], [104.0, 100.0]]), ["left", "right"], 400, 300)
>>> pl.overlaps, boxes_overlap(pl.boxes[0], pl.boxes[1])
(0, False)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Placement", "place_labels", "chart_placement", "limit_boxes", "text_size", "boxes_overlap"]

#: Width of an average character in units of the font size (sans-serif, a little generous).
CHAR_WIDTH = 0.62
#: Clear distances (px) from the point to the label's near edge, nearest first.
DISTANCES = (5.0, 12.0, 22.0, 36.0, 54.0, 76.0, 100.0)
#: Directions (degrees), preferred first: right, left, above, below, then the diagonals.
ANGLES = (0, 180, 90, 270, 30, 150, 330, 210, 60, 120, 300, 240)
#: A leader line is drawn when the label's near edge is farther than this (px).
LEADER_PX = 16.0


@dataclass
class Placement:
    """Label centres as offsets from their points (px, y up), their boxes, leader flags."""

    offsets: np.ndarray          # (n, 2) label centre minus point, px
    boxes: list[tuple[float, float, float, float]]  # (x0, y0, x1, y1) per label, px, y up
    leaders: list[bool]
    overlaps: int                # labels that could not be placed clear of everything


def text_size(text: str, font_px: float) -> tuple[float, float]:
    """Estimated (width, height) in px of one line of ``text`` at ``font_px``, with padding."""
    return CHAR_WIDTH * font_px * max(1, len(text)) + 4.0, 1.3 * font_px + 2.0


def boxes_overlap(a, b, gap: float = 0.0) -> bool:
    """Whether boxes ``(x0, y0, x1, y1)`` overlap (or come closer than ``gap``)."""
    return not (a[2] + gap <= b[0] or b[2] + gap <= a[0] or a[3] + gap <= b[1] or b[3] + gap <= a[1])


def _area(a, b) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return max(0.0, w) * max(0.0, h)


def _candidates(p, w, h):
    for d in DISTANCES:
        for ang in ANGLES:
            c, s = math.cos(math.radians(ang)), math.sin(math.radians(ang))
            cx = p[0] + c * (d + w / 2) if abs(c) > 1e-9 else p[0]
            cy = p[1] + s * (d + h / 2) if abs(s) > 1e-9 else p[1]
            yield d, (cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2)


def _cost(box, gap, placed, markers, width, height) -> float:
    """Overlap area (the box grown by ``gap``) with placed labels and markers, plus the box's
    area outside the plot."""
    inside = (max(box[0], 0.0), max(box[1], 0.0), min(box[2], width), min(box[3], height))
    outside = (box[2] - box[0]) * (box[3] - box[1]) - max(0.0, inside[2] - inside[0]) * max(0.0, inside[3] - inside[1])
    grown = (box[0] - gap, box[1] - gap, box[2] + gap, box[3] + gap)
    return outside + sum(_area(grown, b) for b in placed) + sum(_area(grown, m) for m in markers)


def place_labels(points: np.ndarray, texts: list[str], width: float, height: float, *, font_px: float = 11.0,
                 marker_px: float = 6.0, gap: float = 2.0, obstacles=()) -> Placement:
    """Place one label per point inside a ``width`` x ``height`` px plot area.

    Parameters
    ----------
    points : ndarray (n, 2)
        Point positions in px from the plot area's lower-left corner (y up).
    texts : list of str
        One label per point.
    width, height : float
        The plot area in px.
    font_px, marker_px, gap : float
        Label font size, marker half-size and the clear gap kept around labels, px.
    obstacles : sequence of boxes
        Other things labels must not cover (lines, texts), ``(x0, y0, x1, y1)`` px.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(texts) != len(pts):
        raise ValueError(f"place_labels: {len(pts)} points but {len(texts)} labels")
    n = len(pts)
    markers = [(x - marker_px, y - marker_px, x + marker_px, y + marker_px) for x, y in pts] + list(obstacles)
    crowd = [int(np.sum(np.hypot(*(pts - pts[i]).T) < 60.0)) for i in range(n)]
    order = sorted(range(n), key=lambda i: (-crowd[i], i))
    boxes: list = [None] * n
    leaders = [False] * n
    placed: list = []
    overlaps = 0
    for i in order:
        w, h = text_size(texts[i], font_px)
        best, best_cost, best_d = None, math.inf, 0.0
        for d, box in _candidates(pts[i], w, h):
            cost = _cost(box, gap, placed, markers, width, height)
            if cost < best_cost - 1e-9:
                best, best_cost, best_d = box, cost, d
                if cost == 0.0:
                    break
        overlaps += int(best_cost > 0.0)
        boxes[i] = best
        leaders[i] = best_d > LEADER_PX
        placed.append(best)
    offsets = np.array([[(b[0] + b[2]) / 2 - p[0], (b[1] + b[3]) / 2 - p[1]] for b, p in zip(boxes, pts)])
    return Placement(offsets.reshape(-1, 2), boxes, leaders, overlaps)


def limit_boxes(chart, axes, width: float, height: float, font_px: float) -> dict:
    """Where the budget and target texts sit, px boxes: the budget's at the top of its line, to
    the right; the target's at the right end of its line, above it."""
    out = {}
    if chart.budget:
        bx, _ = axes.to_px(chart.budget[0], 10 ** axes.y_lo, width, height)
        w, h = text_size(chart.budget[1], font_px)
        x0 = bx + 3 if bx + 3 + w <= width else bx - 3 - w
        out["budget"] = (x0, height - h - 1, x0 + w, height - 1)
    if chart.target:
        _, ty = axes.to_px(10 ** axes.x_lo, chart.target[0], width, height)
        w, h = text_size(chart.target[1], font_px)
        out["target"] = (width - w - 2, ty + 1, width - 2, ty + 1 + h)
    return out


def _segment_boxes(xy: list[tuple[float, float]], half: float = 1.5) -> list:
    """Thin boxes along a staircase (horizontal then vertical steps) through ``xy``."""
    boxes = []
    for (x0, y0), (x1, y1) in zip(xy, xy[1:]):
        boxes.append((min(x0, x1), y0 - half, max(x0, x1), y0 + half))
        boxes.append((x1 - half, min(y0, y1), x1 + half, max(y0, y1)))
    return boxes


def _line_boxes(xy: list[tuple[float, float]], step: float = 6.0, half: float = 1.5) -> list:
    """Small boxes along the straight segments through ``xy``."""
    boxes = []
    for (x0, y0), (x1, y1) in zip(xy, xy[1:]):
        n = max(1, int(math.hypot(x1 - x0, y1 - y0) / step))
        for k in range(n + 1):
            x, y = x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n
            boxes.append((x - half, y - half, x + half, y + half))
    return boxes


def chart_placement(chart, width: float, height: float, font_px: float) -> Placement:
    """The labels of ``chart`` in a ``width`` x ``height`` px plot area, clear of the points,
    the front's steps and the limit texts (what both renderers draw)."""
    from pipeline.charts.model import chart_axes, chart_fronts, point_label

    axes = chart_axes(chart)
    px = np.array([axes.to_px(p.x, p.y, width, height) for p in chart.points]).reshape(-1, 2)
    obstacles = list(limit_boxes(chart, axes, width, height, font_px).values())
    for front in chart_fronts(chart):
        obstacles += _segment_boxes([tuple(px[i]) for i in front])
    if chart.connect:
        for s in chart.series_names():
            idx = [i for i, p in enumerate(chart.points) if p.series == s]
            obstacles += _line_boxes([tuple(px[i]) for i in idx])
    return place_labels(px, [point_label(p) for p in chart.points], width, height, font_px=font_px,
                        obstacles=obstacles)
