"""Figures for people (mm). The only module that imports matplotlib; it draws with the
object API (``matplotlib.figure.Figure``), so it runs headless with no display."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from .results import write_atomic
from .solve import Design

STYLES = {
    "test-pose": dict(color="tab:red", ls="-", lw=2.0),
    "D": dict(color="tab:blue", ls="--", lw=1.5),
    "A": dict(color="tab:green", ls="-.", lw=1.5),
    "E": dict(color="tab:purple", ls=":", lw=2.0),
    "T": dict(color="tab:brown", ls=(0, (5, 1, 1, 1)), lw=1.5),
    "condition": dict(color="tab:gray", ls=(0, (3, 1)), lw=1.5),
}
LABELS = {"test-pose": "Test-pose approach", "D": "D-optimality", "A": "A-optimality",
          "E": "SVD approach (E-optimality)", "T": "T-optimality", "condition": "Condition number"}


def path_coordinate(position_m: np.ndarray) -> tuple[np.ndarray, str]:
    """Abscissa of the test poses (mm): the Cartesian coordinate that varies most, when it is
    monotonic along the poses (x for the paper's line), else the arc length along them."""
    p = np.asarray(position_m) * 1e3
    k = int(np.argmax(np.ptp(p, axis=0)))
    d = np.diff(p[:, k])
    if p.shape[0] > 1 and (np.all(d > 0) or np.all(d < 0)):
        return p[:, k], f"{'xyz'[k]} (mm)"
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    return s, "arc length along the test poses (mm)"


def draw_error_bands(ax: Axes, x_mm: np.ndarray, designs: list[Design], xlabel: str) -> None:
    """``+/- sqrt(rho)`` (mm) around the target trajectory for each design, maxima labelled."""
    ax.axhline(0.0, color="k", lw=1.0, label="Target trajectory")
    for d in designs:
        e = d.scores.rms_error_m * 1e3
        style = STYLES[d.criterion]
        ax.plot(x_mm, e, label=LABELS[d.criterion], **style)
        ax.plot(x_mm, -e, **style)
        j = int(np.argmax(e))
        ax.plot([x_mm[j]], [e[j]], "o", color=style["color"], ms=4)
        ax.annotate(f"{e[j]:.3f}", (x_mm[j], e[j]), textcoords="offset points", xytext=(4, 4),
                    color=style["color"], fontsize=9)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(r"$\pm\sqrt{\rho}$ (mm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")


def fig1(position_m: np.ndarray, designs: list[Design], m_values: list[int]) -> Figure:
    """The paper's Fig. 1: one panel per m, the error bands of every criterion's plan."""
    x, xlabel = path_coordinate(position_m)
    fig = Figure(figsize=(5.5 * len(m_values), 4.5), layout="constrained")
    axes = fig.subplots(1, len(m_values), squeeze=False)[0]
    top = max(d.scores.max_rms_error_m for d in designs if d.m in m_values) * 1e3
    for ax, m, letter in zip(axes, m_values, "abcdefghij"):
        draw_error_bands(ax, x, [d for d in designs if d.m == m], xlabel)
        ax.set_ylim(-1.25 * top, 1.25 * top)
        ax.set_title(f"({letter}) {m} calibration experiment{'s' if m > 1 else ''}")
    return fig


def save_figure(fig: Figure, path: Path) -> None:
    """Save atomically in the format of the file's suffix (png, pdf, svg)."""
    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix[1:], dpi=150)
    write_atomic(Path(path), buf.getvalue())
