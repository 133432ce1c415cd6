"""Saving matplotlib figures (headless): the one place that writes a figure to a PNG."""

from __future__ import annotations

from pathlib import Path

__all__ = ["save_figure"]


def save_figure(fig, path, dpi: int = 100, tight: bool = True) -> Path:
    """Lay out ``fig`` (``tight``: matplotlib's tight layout; False keeps a figure placed by hand),
    write it to ``path`` (parent folders created) and close it.

    Examples
    --------
    >>> import matplotlib; matplotlib.use("Agg")
    >>> import matplotlib.pyplot as plt, tempfile, os
    >>> p = save_figure(plt.figure(), os.path.join(tempfile.mkdtemp(), "a", "f.png"), dpi=20)
    >>> p.exists()
    True
    """
    import matplotlib.pyplot as plt

    if tight:
        fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
