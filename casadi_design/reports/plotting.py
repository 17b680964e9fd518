"""Figures for people (mm). The only module that imports matplotlib; it draws with the
object API (``matplotlib.figure.Figure``), so it runs headless with no display."""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib import rc_context
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter, NullLocator

from ..measures.criteria import CRITERIA
from ..plan.design import Design
from ..records.files import write_atomic

if TYPE_CHECKING:
    from ..execution.sweep import Sweep

def is_path(position_m: np.ndarray) -> bool:
    """Whether the test poses follow a path (a line, polyline or arc: no step turns back by more
    than 90 deg from the one before), rather than separate points such as drilling holes, whose
    file order draws a line that means nothing."""
    steps = np.diff(np.asarray(position_m, dtype=float), axis=0)
    return bool(np.all(np.einsum("ij,ij->i", steps[1:], steps[:-1]) >= 0))


def pose_labels(position_m: np.ndarray) -> list[str]:
    """``x`` over ``y`` of each test pose (mm, two lines), to label the groups of poses off a
    path."""
    xy = np.round(np.asarray(position_m)[:, :2] * 1e3) + 0.0  # + 0.0: no "-0"
    return [f"{x:.0f}\n{y:.0f}" for x, y in xy]


def path_coordinate(position_m: np.ndarray) -> tuple[np.ndarray, str]:
    """Abscissa of the test poses (mm): the Cartesian coordinate that varies most, when it is
    monotonic along the poses (x for the paper's line), else the arc length along them."""
    p = np.asarray(position_m) * 1e3
    k = int(np.argmax(np.ptp(p, axis=0)))
    d = np.diff(p[:, k])
    if p.shape[0] > 1 and (np.all(d > 0) or np.all(d < 0)):
        return p[:, k], f"{'xyz'[k]} (mm)"
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    return arc, "arc length along the test poses (mm)"


#: Style of a plan given by the user (``casadi-design evaluate``).
USER_STYLE = {"color": "tab:orange", "ls": "-", "lw": 5.0, "alpha": 0.5}  # wide: shows beneath an equal curve
#: Style of the reference line "repeat the best single pose m times".
REPEAT_STYLE = {"color": "k", "ls": ":", "lw": 1.2}
#: Style of the certified bound of the test-pose error ("best possible").
BOUND_STYLE = {"color": "tab:red", "ls": "--", "lw": 1.0, "alpha": 0.7}


@dataclass(frozen=True)
class Band:
    """One curve of a band plot: its label, line style and ``sqrt(rho_j)`` (m) per test pose."""

    label: str
    style: dict
    rms_error_m: np.ndarray

    @classmethod
    def of(cls, design: Design) -> Band:
        crit = CRITERIA[design.criterion]
        return cls(crit.legend, crit.style, design.scores.rms_error_m)


#: Font size of the labels of the maxima (pt).
PEAK_FONTSIZE = 8.5
#: A label raised more than this many label heights above its point gets a leader line to it.
LEADER_AFTER = 1.0


def label_maxima(ax: Axes, peaks: list[tuple[float, float, str]],
                 bars: list[tuple[float, float, float]] | None = None) -> None:
    """Label each series' maximum ``(x, y, colour)`` (data units) with its value, the highest
    first, just above it (lines: to its right, or left at the right edge) and above the
    ``bars`` ``(left, right, top)`` under it; a label that
    would cover one placed before goes below its point (lines, when it stays above ``y = 0``,
    the target line; in a bar it would be unreadable) or else up, until it is clear, with a
    line down to its point when raised more than :data:`LEADER_AFTER` label heights. Sizes are
    estimated from the axes' size and limits when called (set the limits first), so the
    labels of nearly equal maxima do not print over each other."""
    fig = ax.get_figure()
    box = ax.get_position()
    size = np.array([box.width * fig.get_figwidth(), box.height * fig.get_figheight()]) * 72  # pt
    limits = np.array([ax.get_xlim(), ax.get_ylim()])  # [[x0, x1], [y0, y1]]
    low, span = limits[:, 0], limits[:, 1] - limits[:, 0]
    h, gap = 1.25 * PEAK_FONTSIZE, 3.0
    zero = -low[1] / span[1] * size[1]  # y = 0 (pt)
    placed: list[tuple[float, float, float, float]] = []  # left, bottom, right, top (pt)

    def covered(left: float, bottom: float, w: float) -> list[float]:
        """The tops of the labels placed that the box (left, bottom, w, h) would cover."""
        return [t for l, b, r, t in placed if left < r and l < left + w and bottom < t and b < bottom + h]

    def free(left: float, bottom: float, w: float) -> bool:
        return not covered(left, bottom, w)

    for x, y, colour in sorted(peaks, key=lambda p: -p[1]):
        text = f"{y:.3f}"
        px, py = (np.array([x, y]) - low) / span * size
        w = 0.6 * PEAK_FONTSIZE * len(text)
        left = px - w / 2 if bars is not None else px + gap if px + gap + w <= size[0] else px - gap - w
        under = [(top - low[1]) / span[1] * size[1] for x0, x1, top in bars or ()
                 if left < (x1 - low[0]) / span[0] * size[0] and (x0 - low[0]) / span[0] * size[0] < left + w]
        above, below = max([py, *under]) - py + gap, -gap - h
        if free(left, py + above, w):
            dy = above
        elif bars is None and py + below >= zero + gap and free(left, py + below, w):
            dy = below
        else:
            dy = above
            while not free(left, py + dy, w):
                dy = max(covered(left, py + dy, w)) - py + 1
        placed.append((left, py + dy, left + w, py + dy + h))
        leader = {"arrowprops": {"arrowstyle": "-", "color": colour, "lw": 0.6, "shrinkA": 0, "shrinkB": 1}
                  } if dy > gap + LEADER_AFTER * h else {}  # far from its point: a line tells whose it is
        ax.annotate(text, (x, y), textcoords="offset points", xytext=(left + w / 2 - px, dy), ha="center",
                    va="bottom", color=colour, fontsize=PEAK_FONTSIZE, **leader)


def draw_errors_per_pose(ax: Axes, bars: list[tuple[str, dict, np.ndarray]], ylabel: str,
                         labels: list[str] | None = None, top: float | None = None, legend: bool = True) -> None:
    """One group per test pose (a drilling hole), one bar per series ``(label, style, values in
    mm)``, each series' maximum labelled (:func:`label_maxima`); ``top``: the upper limit of the
    axis (mm; None: the largest value with room for the labels); ``legend`` below the axes."""
    s = len(bars[0][2])
    width = 0.8 / len(bars)
    x = np.arange(1, s + 1)
    peaks, tops = [], []
    for i, (label, style, e) in enumerate(bars):
        at = x - 0.4 + width * (i + 0.5)
        ax.bar(at, e, width, label=label, color=style.get("color"), alpha=0.85)
        j = int(np.nanargmax(e))
        peaks.append((at[j], e[j], style.get("color")))
        tops += [(a - width / 2, a + width / 2, v) for a, v in zip(at, e) if np.isfinite(v)]
    every = max(1, s // 20)  # at most ~20 tick labels
    ax.set_xticks(x[::every], (labels or [str(v) for v in x])[::every], fontsize=8)
    ax.set_xlabel("test pose: x over y (mm), in file order" if labels else "test pose (one group per pose, in file order)")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3, axis="y")
    ax.set_ylim(0, 1.25 * (max(p[1] for p in peaks) if top is None else top))
    label_maxima(ax, peaks, tops)
    if legend:  # below the axes, in rows: the groups fill the width, so no corner is free of bars
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=min(3, len(bars)))


def draw_error_bands(ax: Axes, x_mm: np.ndarray, bands: list[Band], xlabel: str, top: float,
                     labels: list[str] | None = None) -> None:
    """``+/- sqrt(rho)`` (mm) around the target trajectory for each band, maxima labelled
    (:func:`label_maxima`), the axis to ``+/- 1.25 top`` (mm); test poses off a path
    (``labels`` of the poses given): ``sqrt(rho)`` per pose, one group per pose. No legend:
    the figure has one for all its panels (:func:`error_bands_figure`)."""
    if labels is not None:
        draw_errors_per_pose(ax, [(b.label, b.style, b.rms_error_m * 1e3) for b in bands],
                             r"$\sqrt{\rho}$ (mm)", labels, top, legend=False)
        return
    ax.axhline(0.0, color="k", lw=1.0, label="Target trajectory")
    peaks = []
    for d in bands:
        e = d.rms_error_m * 1e3
        style = d.style
        ax.plot(x_mm, e, label=d.label, **style)
        ax.plot(x_mm, -e, **style)
        j = int(np.argmax(e))
        ax.plot([x_mm[j]], [e[j]], "o", color=style["color"], ms=4)
        peaks.append((x_mm[j], e[j], style["color"]))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(r"$\pm\sqrt{\rho}$ (mm)")
    ax.grid(alpha=0.3)
    ax.set_ylim(-1.25 * top, 1.25 * top)
    label_maxima(ax, peaks)


def error_bands_figure(position_m: np.ndarray, panels: list[tuple[str, list[Design | Band]]]) -> Figure:
    """Panels ``(title, bands)`` of error bands (:func:`draw_error_bands`) on one scale, the
    largest error of them all, with one legend below them."""
    x, xlabel = path_coordinate(position_m)
    panels = [(title, [b if isinstance(b, Band) else Band.of(b) for b in bands]) for title, bands in panels]
    fig = Figure(figsize=(5.5 * len(panels) if len(panels) > 1 else 6.5, 5.0), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    top = max(float(np.max(b.rms_error_m)) for _, bands in panels for b in bands) * 1e3
    labels = None if is_path(position_m) else pose_labels(position_m)
    for ax, (title, bands) in zip(axes, panels):
        draw_error_bands(ax, x, bands, xlabel, top, labels)
        ax.set_title(title)
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="outside lower center", ncol=min(len(names), 3 if len(panels) == 1 else 4),
               fontsize=8)
    return fig


def fig1(position_m: np.ndarray, designs: list[Design], m_values: list[int]) -> Figure:
    """The paper's Fig. 1: one panel per m, the error bands of every criterion's plan."""
    return error_bands_figure(position_m, [
        (f"({letter}) {m} calibration experiment{'s' if m > 1 else ''}", [d for d in designs if d.m == m])
        for m, letter in zip(m_values, "abcdefghij")])


def bands_figure(position_m: np.ndarray, bands: list[Design | Band], title: str) -> Figure:
    """One panel of error bands, e.g. a user's plan against the optimal plans of the same m."""
    return error_bands_figure(position_m, [(title, bands)])


def draw_max_error_vs_m(ax: Axes, sweep: Sweep, log: bool = False) -> None:
    """Max over the test poses of ``sqrt(rho)`` (mm) against m, one line per criterion, the
    reference "repeat the best single pose" ``e(m_ref) sqrt(m_ref / m)`` and, when the test-pose
    designs carry it, their certified bound (dashed; it falls as ``1 / sqrt(m)``)."""
    ms = np.array(sweep.m_values)
    for c in sweep.criteria:
        e = np.array([sweep.designs[c, m].scores.max_rms_error_m for m in ms]) * 1e3
        style = {**CRITERIA[c].style, "ls": "-" if c == "test-pose" else CRITERIA[c].style["ls"]}
        ax.plot(ms, e, marker="o", ms=4, label=CRITERIA[c].legend, **style)
    if sweep.reference is not None:
        m_ref = sweep.reference.m
        mm = np.linspace(min(m_ref, ms.min()), ms.max(), 200)  # from the plan it repeats
        label = (r"Best single pose repeated m times ($e_1/\sqrt{m}$)" if m_ref == 1 else
                 f"Best {m_ref}-pose plan repeated ($e_{{{m_ref}}}\\sqrt{{{m_ref}/m}}$)")
        ax.plot(mm, [sweep.repeat_reference_m(v) * 1e3 for v in mm], **REPEAT_STYLE, label=label)
    if "test-pose" in sweep.criteria and all(sweep.designs["test-pose", m].bound for m in ms):
        ax.plot(ms, [sweep.designs["test-pose", m].bound.value * 1e3 for m in ms], **BOUND_STYLE,
                label="Best possible with m experiments (certified bound)")
    ticks = sorted(set(ms.tolist()) | ({sweep.reference.m} if sweep.reference is not None else set()))
    if log:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(ticks, [str(m) for m in ticks])
        ax.xaxis.set_minor_locator(NullLocator())
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.yaxis.set_minor_locator(LogLocator(subs=np.arange(1.0, 10.0)))
        ax.yaxis.set_minor_formatter(NullFormatter())
    else:
        ax.set_xticks(ticks)
        ax.set_ylim(0, 1.05 * ax.get_ylim()[1])  # room above the highest point
    ax.set_xlabel("number of calibration experiments m")
    ax.set_ylabel(r"max over test poses of $\sqrt{\rho}$ (mm)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)


def sweep_figure(sweep: Sweep, log: bool = False) -> Figure:
    """Accuracy against the number of experiments for every criterion of a sweep."""
    fig = Figure(figsize=(6.5, 4.5), layout="constrained")
    ax = fig.subplots()
    draw_max_error_vs_m(ax, sweep, log)
    ax.set_title("Worst expected error along the test poses vs number of experiments", fontsize=10)
    return fig


def save_figures(fig: Figure, paths: list[Path]) -> None:
    """Save atomically in the format of each file's suffix (png, pdf, svg).

    The layout is computed for the first file and kept for the others (constrained layout
    takes most of the time of a save, and gives the same result every time): the figure has
    no layout engine from the second file on. Not even the placeholder that
    ``set_layout_engine("none")`` leaves: ``savefig`` draws a figure with any engine once
    before it prints (to lay it out), a draw of every artist that lays out nothing here (the
    PDF of the paper's fig1 0.12 -> 0.09 s of CPU, the same bytes).
    """
    for k, path in enumerate(paths):
        if k == 1:
            # None, not "none"; None means no engine only while these rcParams are off
            with rc_context({"figure.autolayout": False, "figure.constrained_layout.use": False}):
                fig.set_layout_engine(None)
        buf = io.BytesIO()
        fig.savefig(buf, format=Path(path).suffix[1:], dpi=150)
        write_atomic(Path(path), buf.getvalue())


def write_figures(out: Path, stem: str, fig: Figure, suffixes: tuple[str, ...] = ("png", "pdf")) -> list[str]:
    """``fig`` as ``out/stem.<suffix>`` for each of ``suffixes`` (:func:`save_figures`); returns
    the file names."""
    save_figures(fig, [out / f"{stem}.{suffix}" for suffix in suffixes])
    return [f"{stem}.{suffix}" for suffix in suffixes]


def validation_figure(validation) -> Figure:
    """Predicted ``sqrt(rho)`` (lines) and simulated RMS error with its interval (markers), mm,
    along the test poses of a virtual calibration (a :class:`casadi_design.virtual.Validation`):
    one panel per m."""
    from ..virtual.statistics import CONFIDENCE

    x, xlabel = path_coordinate(validation.problem.test_poses.position_m)
    ms = sorted({p.plan.m for p in validation.plans})
    fig = Figure(figsize=(5.5 * len(ms), 4.5), layout="constrained")
    axes = fig.subplots(1, len(ms), squeeze=False)[0]
    every = max(1, -(-len(x) // 15))  # at most 15 labels: they stay legible at 100 rows
    for ax, m in zip(axes, ms):
        for i, p in enumerate(p for p in validation.plans if p.plan.m == m):
            crit = CRITERIA[p.plan.criterion]
            e = p.empirical_rms_m * 1e3
            ax.plot(x, p.predicted_rms_m * 1e3, label=f"{crit.legend}: sqrt(rho)", **crit.style)
            ax.errorbar(x[::every], e[::every],
                        yerr=np.abs(np.vstack([p.ci_low_m, p.ci_high_m]) * 1e3 - e)[:, ::every],
                        fmt="o", ms=3, capsize=2, color=crit.style["color"],
                        label="simulated RMS and interval" if i == 0 else "_nolegend_")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("RMS error after compensation (mm)")
        ax.set_ylim(bottom=0)
        ax.set_title(f"m = {m}: {validation.trials} virtual calibrations, "
                     f"{round(100 * CONFIDENCE)}% intervals")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    return fig


def poses_figure(problem, designs: list[Design]) -> Figure:
    """The robot in every experiment of each design (one 3-D panel each, mm): its capsules as
    thick lines (one colour per experiment), the obstacles, the tracker and its beams to the
    reflectors, and the test path. The view holds the robot, the tracker and the test path
    (5 % more each way); each obstacle draws itself in it
    (:meth:`casadi_design.cell.obstacles.Obstacle.draw`: the floor becomes its bottom)."""
    from ..cell.cell import world_capsules

    cell, robot = problem.cell, problem.robot
    # no constrained layout: it places the 3-D panels so that their titles are cut off
    fig = Figure(figsize=(6.0 * len(designs), 6.0))
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown",
               "tab:pink", "tab:gray", "tab:olive", "tab:cyan"]
    path = problem.test_poses.position_m * 1e3
    for k, d in enumerate(designs):
        ax = fig.add_subplot(1, len(designs), k + 1, projection="3d")
        points = [path]
        for i, q in enumerate(d.Q):
            colour = colours[i % len(colours)]
            for a, b, r, _ in world_capsules(cell, robot, q):
                seg = np.array([a, b]) * 1e3
                ax.plot(*seg.T, color=colour, lw=max(1.0, 60 * r), alpha=0.45, solid_capstyle="round")
                points.append(seg)
            P = np.asarray(problem.model.points(q), dtype=float).T * 1e3
            ax.scatter(*P.T, color=colour, s=12, depthshade=False)
            if cell.spec.tracker is not None:
                t = np.array(cell.spec.tracker.position_m) * 1e3
                for p in P:
                    ax.plot(*np.array([t, p]).T, color=colour, lw=0.6, ls="--")
        if cell.spec.tracker is not None:
            t = np.array(cell.spec.tracker.position_m) * 1e3
            ax.scatter(*t, marker="*", s=120, color="k", label="tracker")
            points.append(t[None])
        ax.plot(*path.T, color="k", lw=1.0, marker=".", ms=5, label="test poses")
        allp = np.vstack(points)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        pad = 0.05 * (hi - lo).max()
        lo, hi = lo - pad, hi + pad
        for o in cell.obstacles:
            lo, hi = o.draw(ax, lo, hi)
        for setter, a, b in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), lo, hi):
            setter(a, b)
        ax.set_box_aspect(hi - lo, zoom=0.85)  # true proportions, room for the z label
        ax.view_init(elev=25, azim=-70)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
        ax.set_title(f"{CRITERIA[d.criterion].legend}, m = {d.m}: "
                     f"{d.scores.max_rms_error_m * 1e3:.4f} mm", fontsize=10)
        ax.legend(fontsize=8, loc="upper left")
    fig.subplots_adjust(left=0.0, right=0.95, bottom=0.02, top=0.95, wspace=0.08)
    return fig


#: Styles of the identification figure's series.
NOMINAL_STYLE = {"color": "tab:gray"}
CALIBRATED_STYLE = {"color": "tab:blue"}
PREDICTED_STYLE = {"color": "tab:green"}
AXIS_STYLES = ({"color": "tab:red"}, {"color": "tab:green"}, {"color": "tab:blue"})


REGISTRATION_STYLE = {"color": "tab:orange", "lw": 4.0, "alpha": 0.5}  # wide: shows beneath an equal nominal curve


def identification_figure(calibration) -> Figure:
    """The identification of measured data (a :class:`casadi_design.identification.calibrate.
    Calibration`), mm: (a) residuals per experiment and axis (RMS over its points, one marker
    per axis; outliers marked), (b) the validation errors of each model sorted (the curve of
    their distribution: registration only, nominal and calibrated in the training frame, or
    each re-registered when the tracker moved, the prediction; poses outside the training range marked), (c) at the test poses the predicted
    ``sqrt(rho)``, and the measured error where a validation pose is a test pose."""
    c = calibration
    fig = Figure(figsize=(16, 4.5), layout="constrained")
    ax_r, ax_v, ax_t = fig.subplots(1, 3)
    axes = [a for a in range(3) if np.isfinite(c.residual_axes_m[:, :, a]).any()]
    x = np.arange(1, c.measurements.m + 1)
    for k, a in enumerate(axes):
        e = np.sqrt(np.nanmean(c.residual_axes_m[:, :, a] ** 2, axis=1)) * 1e3
        ax_r.plot(x + 0.2 * (k - 1), e, "o", ms=3.5, label=f"{'xyz'[a]} residual", **AXIS_STYLES[a])
    out = ~c.fit.used
    if out.any():
        top = np.nanmax(np.sqrt(np.nanmean(c.residual_axes_m[out][:, :, axes] ** 2, axis=1)), axis=1) * 1e3
        ax_r.plot(x[out], top, "kx", ms=8, label="outlier (not in the fit)")
    every = max(1, -(-len(x) // 15))  # at most 15 labels: they stay legible at 100 rows
    ax_r.set_xticks(x[::every], [str(line) for line in c.measurements.lines][::every], fontsize=8)
    ax_r.set_ylabel("residual, RMS over the points (mm)")
    ax_r.set_xlabel("experiment (row of the file)")
    ax_r.grid(alpha=0.3)
    ax_r.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=4)
    ax_r.set_title(f"(a) residuals ({c.model} model): RMS {np.sqrt(np.mean(c.residual_rms_m[c.fit.used] ** 2)) * 1e3:.4f} mm")
    v = c.validation
    if v is None:
        ax_v.text(0.5, 0.5, "no validation set (--validation)", ha="center", va="center",
                  transform=ax_v.transAxes)
        ax_v.set_axis_off()
    else:
        n = len(v.lines)
        share = np.arange(1, n + 1) / n * 100
        nominal, registration, calibrated = (getattr(v, f"{k}_m") for k in v.counted)
        for label, style, e in (("registration only", REGISTRATION_STYLE, registration),
                                ("nominal", NOMINAL_STYLE, nominal),
                                ("calibrated", CALIBRATED_STYLE, calibrated),
                                ("predicted", PREDICTED_STYLE, v.predicted_m)):
            order = np.argsort(e)
            ax_v.plot(share, e[order] * 1e3, "-", label=f"{label}: RMS {np.sqrt(np.mean(e**2)) * 1e3:.3f} mm",
                      **({"lw": 1.8} | style))
            if label == "calibrated" and v.out_of_range.any():
                rank = np.flatnonzero(v.out_of_range[order])
                ax_v.plot(share[rank], e[order][rank] * 1e3, "o", mfc="none", ms=6, color="k",
                          label=f"calibrated, outside the training range ({int(v.out_of_range.sum())})")
        ax_v.set_xlabel("share of the validation poses with a smaller error (%)")
        ax_v.set_ylabel("error, RMS over the points (mm)")
        ax_v.grid(alpha=0.3)
        ax_v.legend(fontsize=8, loc="upper left")
        ax_v.set_title(f"(b) the {n} validation poses, errors sorted "
                       f"({'each model re-registered: the tracker moved' if v.moved else 'training frame'})")
    bars = [("predicted sqrt(rho)", PREDICTED_STYLE, c.predicted_rms_m * 1e3)]
    measured = c.test_pose_errors_m
    if measured is not None:
        bars.append(("measured (validation)", CALIBRATED_STYLE, measured * 1e3))
    position = c.problem.test_poses.position_m
    draw_errors_per_pose(ax_t, bars, "error after calibration (mm)",
                         None if is_path(position) else pose_labels(position))
    ax_t.set_title(f"(c) the {len(c.predicted_rms_m)} test poses")
    return fig
