"""Draw docs/images/layers.png: the layers of IrisTac and the stage registry.

Run from the repository root: ``python docs/figures/layers.py``. The layers drawn here are
the ones ``tests/test_layers.py`` checks (its ``LAYERS`` table is read, so the figure cannot
drift from the test).
"""

from __future__ import annotations

import ast
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "images" / "layers.png"

#: What each layer holds, in words (the test's LAYERS table gives the names and the order).
CONTENTS = {
    "command line and benchmarks": ["pipeline/cli/  (thin: one module per command)", "pipeline/bench/  (benchmarks)"],
    "entry points": ["pipeline/workflows/\n(run, reconstruct, batch, demo, ...)",
                     "pipeline/streaming/\n(a recording a chunk at a time)", "pipeline/live/"],
    "stage registry": ["synthesize", "calibrate", "capture", "normals", "depth"],
    "calibration and capture": ["calibration/\n(contacts, light models, LUT, MLP)",
                                "pipeline/capture/\n(ring, emulator, plan, cameras, videos)",
                                "pipeline/solving/\n(lights, regions, frame solvers)"],
    "physics and numerics": ["sim/\n(tracer, renderer)", "pipeline/normals/\n(solvers)",
                             "pipeline/depth/\n(integrators)", "pipeline/frame_pipeline/\n(normals, then depth)",
                             "pipeline/results/", "pipeline/charts/"],
    "base": ["errors", "frames", "hashing", "identity", "store", "streamed", "capture", "camera", "modes", "registry",
             "threads"],
    "schemas": ["data_schemas/  (JSON Schemas of every file and config)"],
}
COLOURS = ["#e8e8f4", "#dde9f7", "#e2f0e0", "#f7ecd9", "#f6dede", "#ece2f4", "#eeeeee"]


def layers() -> list[tuple[str, list[str]]]:
    """The LAYERS table of tests/test_layers.py, read without importing it."""
    tree = ast.parse((ROOT / "tests" / "test_layers.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "LAYERS" for t in node.targets):
            return ast.literal_eval(node.value)
    raise SystemExit("tests/test_layers.py has no LAYERS table")


def box(ax, x, y, w, h, text, fc, fontsize=8.5, weight="normal", ec="#555555", ls="-"):
    ax.add_patch(FancyBboxPatch((x, y), w, h, boxstyle="round,pad=0.02,rounding_size=0.08", fc=fc, ec=ec,
                                lw=0.9, ls=ls))
    ax.text(x + w / 2, y + h / 2, text, ha="center", va="center", fontsize=fontsize, weight=weight, wrap=True)


def arrow(ax, x0, y0, x1, y1, colour="#333333", style="-|>", ls="-", text=None):
    ax.add_patch(FancyArrowPatch((x0, y0), (x1, y1), arrowstyle=style, mutation_scale=10, color=colour, lw=1.0,
                                 ls=ls))
    if text:
        ax.text((x0 + x1) / 2 + 0.1, (y0 + y1) / 2, text, fontsize=7, color=colour, va="center")


def main() -> Path:
    table = layers()
    order = list(reversed(table))  # top of the figure: the highest layer
    band_h, gap, width, left = 1.05, 0.28, 13.0, 1.6
    fig_h = len(order) * (band_h + gap) + 0.9
    fig, ax = plt.subplots(figsize=(15.5, fig_h))
    ax.set_xlim(0, left + width + 0.3)
    ax.set_ylim(0, fig_h)
    ax.axis("off")
    ys = {}
    for i, (name, prefixes) in enumerate(order):
        y = fig_h - 0.7 - (i + 1) * (band_h + gap) + gap
        ys[name] = y
        colour = COLOURS[(len(order) - 1 - i) % len(COLOURS)]
        ax.add_patch(FancyBboxPatch((left, y), width, band_h, boxstyle="round,pad=0.02,rounding_size=0.12",
                                    fc=colour, ec="#999999", lw=0.8))
        ax.text(left - 0.12, y + band_h / 2, name.replace(" and ", "\nand "), ha="right", va="center", fontsize=9,
                weight="bold")
        items = CONTENTS.get(name, prefixes)
        n = len(items)
        inner = width - 0.3
        w = inner / n - 0.12
        for k, item in enumerate(items):
            x = left + 0.15 + k * (inner / n)
            if name == "stage registry":
                box(ax, x, y + 0.12, w, band_h - 0.24, "", "white")
                ax.text(x + w / 2, y + band_h * 0.64, f"pipeline/stages/{item}.py", ha="center", va="center",
                        fontsize=8, weight="bold")
                ax.text(x + w / 2, y + band_h * 0.36, "SPEC · params · compute\nrun · node", ha="center",
                        va="center", fontsize=7.5)
            elif name == "base":
                box(ax, x, y + 0.2, w, band_h - 0.4, item, "white", fontsize=8.5)
            else:
                box(ax, x, y + 0.15, w, band_h - 0.3, item, "white", fontsize=8.5)
    # Imports point down.
    top, bottom = ys[order[0][0]] + band_h, ys[order[-1][0]]
    arrow(ax, 0.25, top - 0.2, 0.25, bottom + 0.2, colour="#444444")
    ax.text(0.12, (top + bottom) / 2, "imports point down (tests/test_layers.py)", rotation=90, va="center",
            ha="center", fontsize=8, color="#444444")
    # Every entry point goes through the stage registry.
    y_entry, y_stage = ys["entry points"], ys["stage registry"]
    arrow(ax, left + width / 2, y_entry + 0.12, left + width / 2, y_stage + band_h - 0.1,
          text="all go through one stage module per stage: one key per piece of work")
    # The registries name their implementations lazily.
    y_base, y_num = ys["base"], ys["physics and numerics"]
    step9, step4 = (width - 0.3) / 9, (width - 0.3) / 4
    x_reg = left + 0.15 + 7.5 * step9
    for k in (1, 2):  # the solvers and the integrators
        arrow(ax, x_reg, y_base + band_h - 0.2, left + 0.15 + (k + 0.5) * step4, y_num + 0.15, colour="#8a2be2",
              ls="--", style="-")
    ax.text(left + 0.15 + 2.0 * step4, y_base + band_h + 0.1, "the registry names solvers and integrators as "
            "'module:attr': imported when used, never by the base layer", fontsize=7, color="#8a2be2",
            ha="center", va="bottom", bbox=dict(fc="white", ec="none", pad=0.5))
    ax.text(left, fig_h - 0.35, "IrisTac: the layers and the stage registry", fontsize=13, weight="bold")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return OUT


if __name__ == "__main__":
    print(main())
