"""Self-contained HTML reports: sections of image grids and tables, plus the same data as JSON.

The demo and ``compare-modes`` build a :class:`Report` and call :meth:`Report.write`, which
saves ``report.html`` (images referenced as relative PNG paths) and ``report.json``.

Examples
--------
>>> import tempfile, numpy as np
>>> r = Report("Example")
>>> s = r.section("A section", "Some text.")
>>> s.table(["mode", "error (deg)"], [["point", 1.25], ["trichromatic", 3.5]])
>>> s.image("flat", np.zeros((4, 4, 3), np.uint8))
>>> out = r.write(tempfile.mkdtemp(), data={"ok": True})
>>> sorted(p.name for p in out.iterdir())
['images', 'report.html', 'report.json']
"""

from __future__ import annotations

import html
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

__all__ = ["Report", "Section", "to_uint8_image", "format_number"]


def format_number(v: Any, missing: str = "–") -> str:
    """A table cell: floats to 4 significant digits, ``missing`` for None, NaN and Inf.

    Examples
    --------
    >>> format_number(1.23456), format_number(None), format_number(float("nan"), "-"), format_number(3)
    ('1.235', '–', '-', '3')
    """
    if v is None:
        return missing
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.4g}" if np.isfinite(v) else missing
    return str(v)


def to_uint8_image(img: np.ndarray) -> np.ndarray:
    """An ``(H, W)`` or ``(H, W, 3)`` image as uint8; floats are taken to lie in [0, 1]."""
    a = np.asarray(img)
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.uint16:
        return (a >> 8).astype(np.uint8)
    a = np.nan_to_num(a.astype(np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


@dataclass
class _Image:
    caption: str
    path: str


@dataclass
class Section:
    title: str
    text: str = ""
    items: list[tuple[str, Any]] = field(default_factory=list)
    _pending: list[tuple[str, np.ndarray, str]] = field(default_factory=list)

    def table(self, header: Sequence[str], rows: Sequence[Sequence[Any]], caption: str = "") -> None:
        """Add a table; floats are shown with 4 significant digits."""
        self.items.append(("table", (list(header), [list(r) for r in rows], caption)))

    def image(self, caption: str, img: np.ndarray) -> None:
        """Add an image (saved as PNG when the report is written)."""
        self.items.append(("image", len(self._pending)))
        self._pending.append((caption, np.asarray(img), ""))

    def image_file(self, caption: str, path: str | Path) -> None:
        """Add an existing image file (path relative to the report folder, or absolute)."""
        self.items.append(("image_file", (caption, str(path))))

    def paragraph(self, text: str) -> None:
        self.items.append(("text", text))

    def chart(self, chart) -> None:
        """Add an interactive error-against-time chart (:class:`pipeline.charts.model.Chart`): the
        report then carries the chart library (``plotly-<version>.min.js``) beside it, offline."""
        self.items.append(("chart", chart))


class Report:
    """A titled list of sections."""

    def __init__(self, title: str, intro: str = ""):
        self.title = title
        self.intro = intro
        self.sections: list[Section] = []

    def section(self, title: str, text: str = "") -> Section:
        s = Section(title, text)
        self.sections.append(s)
        return s

    def write(self, out_dir: str | Path, data: Any = None) -> Path:
        """Write ``report.html``, its images and ``report.json`` (``data``) into ``out_dir``."""
        import cv2

        out = Path(out_dir)
        img_dir = out / "images"
        img_dir.mkdir(parents=True, exist_ok=True)
        body = [f"<h1>{html.escape(self.title)}</h1>"]
        charts = []
        if self.intro:
            body.append(f"<p>{html.escape(self.intro)}</p>")
        for si, s in enumerate(self.sections):
            body.append(f"<h2>{html.escape(s.title)}</h2>")
            if s.text:
                body.append(f"<p>{html.escape(s.text)}</p>")
            grid: list[str] = []

            def flush_grid():
                if grid:
                    body.append('<div class="grid">' + "".join(grid) + "</div>")
                    grid.clear()

            for kind, payload in s.items:
                if kind == "image":
                    caption, img, _ = s._pending[payload]
                    name = f"s{si:02d}_{payload:03d}_{_slug(caption)}.png"
                    rgb = to_uint8_image(img)
                    bgr = rgb[..., ::-1] if rgb.ndim == 3 else rgb
                    if not cv2.imwrite(str(img_dir / name), np.ascontiguousarray(bgr)):
                        raise OSError(f"{img_dir / name}: could not write PNG")
                    grid.append(_figure(f"images/{name}", caption))
                elif kind == "image_file":
                    caption, path = payload
                    p = Path(path)
                    rel = p.relative_to(out) if p.is_absolute() and out in p.parents else p
                    grid.append(_figure(str(rel), caption))
                elif kind == "table":
                    flush_grid()
                    body.append(_table(*payload))
                elif kind == "chart":
                    from pipeline.charts.page import chart_html

                    flush_grid()
                    charts.append(payload)
                    body.append(chart_html(payload))
                else:
                    flush_grid()
                    body.append(f"<p>{html.escape(payload)}</p>")
            flush_grid()
        head, tail = "", ""
        if charts:
            from pipeline.charts.page import library_tag, render_script

            head, tail = library_tag(out / "report.html", "beside"), render_script(charts)
        page = _PAGE.format(title=html.escape(self.title), body="\n".join(body), head=head, tail=tail)
        (out / "report.html").write_text(page, encoding="utf-8")
        if data is not None:
            (out / "report.json").write_text(json.dumps(data, indent=2, sort_keys=True, default=_json_default),
                                             encoding="utf-8")
        return out


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:40] or "image"


def _figure(src: str, caption: str) -> str:
    return (f'<figure><img src="{html.escape(src)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def _cell(v: Any) -> str:
    if isinstance(v, float) or isinstance(v, np.floating):
        return f"{float(v):.4g}"
    return html.escape(str(v))


def _table(header, rows, caption) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    r = "".join("<tr>" + "".join(f"<td>{_cell(c)}</td>" for c in row) + "</tr>" for row in rows)
    cap = f"<caption>{html.escape(caption)}</caption>" if caption else ""
    return f"<table>{cap}<thead><tr>{h}</tr></thead><tbody>{r}</tbody></table>"


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title><link rel="icon" href="data:,">
<style>
body {{ font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
th, td {{ border: 1px solid #ccc; padding: 4px 8px; text-align: right; }}
th {{ background: #f3f3f3; }} td:first-child, th:first-child {{ text-align: left; }}
caption {{ caption-side: top; text-align: left; font-style: italic; padding: 4px 0; }}
.grid {{ display: flex; flex-wrap: wrap; gap: 12px; }}
figure {{ margin: 0; }} figure img {{ image-rendering: pixelated; width: 240px; border: 1px solid #ddd; }}
figcaption {{ font-size: 12px; max-width: 240px; }}
figure.chart {{ margin: 1em 0; }}
.rec {{ background: #f4f7fb; border-left: 4px solid #1f77b4; padding: 6px 10px; max-width: 860px; }}
.note {{ font-size: 13px; color: #555; max-width: 860px; }}
</style>{head}</head><body>
{body}
{tail}
</body></html>
"""
