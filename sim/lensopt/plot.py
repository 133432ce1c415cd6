"""The optimizer's trajectory as a figure: the objective against evaluations and against seconds."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.figures import save_figure

__all__ = ["trajectory_figure"]


def trajectory_figure(trajectories: dict, path, *, objective: str, label: str = "", start_value=None,
                      bare_value=None) -> Path:
    """Plot one or more trajectories (``{name: Trajectory.as_dict()}``) to the PNG ``path``.

    Left: the best feasible objective after each evaluation (dots: every feasible design's
    value); right: the same against wall seconds. ``start_value`` and ``bare_value`` draw the
    starting design's and the bare LEDs' figures as horizontal lines.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, tr in trajectories.items():
        best = np.array([np.nan if v is None else v for v in tr["best_value"]], dtype=float)
        n = np.arange(1, len(best) + 1)
        line, = axes[0].plot(n, best, lw=1.8, label=name)
        vals = tr.get("values")
        if vals is not None:
            v = np.array([np.nan if x is None else x for x in vals], dtype=float)
            axes[0].plot(n, v, ".", ms=2, alpha=0.35, color=line.get_color())
        axes[1].plot(tr["seconds"], best, lw=1.8, color=line.get_color(), label=name)
    for ax in axes:
        for value, text, style in ((start_value, "start", ":"), (bare_value, "bare LEDs", "--")):
            if value is not None:
                ax.axhline(value, color="0.4", ls=style, lw=1, label=text)
        ax.set_ylabel(objective)
        ax.grid(alpha=0.3)
    axes[0].set_xlabel("evaluations")
    axes[1].set_xlabel("seconds")
    axes[0].set_title(f"{label}best feasible {objective} against evaluations")
    axes[1].set_title("against wall time")
    axes[1].legend(fontsize=8, loc="best")
    return save_figure(fig, path, dpi=100)
