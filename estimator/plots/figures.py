"""Matplotlib for the PNG reports (plots, capture plots, the fleet report, the benches): one headless
backend and one way of writing a figure. Needs the ``plot`` extra."""

from __future__ import annotations

from pathlib import Path

from estimator.errors import EstimatorError


def pyplot():
    """``matplotlib.pyplot`` on the headless Agg backend; EstimatorError naming the extra if it is missing."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise EstimatorError("plotting needs matplotlib: pip install '.[plot]'") from None
    return plt


def save(fig, path: Path, dpi: int = 110) -> Path:
    """Lay out, write ``path`` (PNG) and release the figure; returns the path."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path
