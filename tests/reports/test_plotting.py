"""The labels of the maxima in the error-band figures (Fig. 1, evaluate's figure): each shows
its series' maximum, none covers another or a bar, and the legend is the figure's, below the
panels (drawn with matplotlib's layout, measured in the renderer's pixels)."""

import numpy as np
import pytest
from matplotlib.text import Text

from casadi_design.reports.plotting import LEADER_AFTER, PEAK_FONTSIZE, Band, bands_figure, error_bands_figure

STYLES = [{"color": c, "ls": "-", "lw": 1.5} for c in ("tab:red", "tab:blue", "tab:green", "tab:purple", "tab:gray")]
#: Maxima (mm) of the ABB's Fig. 1 at m = 8: two pairs that differ by 4 and 19 um, at the two
#: ends of the path, and a small one whose mirror (-e) runs close under its label.
PEAKS_MM = (0.019, 0.067, 0.071, 0.088, 0.069)


def _bands(s: int, where: list[int]) -> list[Band]:
    bands = []
    for k, (peak, j, style) in enumerate(zip(PEAKS_MM, where, STYLES)):
        e = np.full(s, 0.9 * peak)
        e[j] = peak
        bands.append(Band(f"series {k}", style, e * 1e-3))
    return bands


def _drawn(fig):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)  # the layout of a saved figure
    # the text's own box (an annotation's window extent also holds its leader line)
    return [(ax, [(t.get_text(), Text.get_window_extent(t, renderer)) for t in ax.texts]) for ax in fig.axes], renderer


def _overlapping(boxes) -> list[tuple[str, str]]:
    return [(a, b) for i, (a, p) in enumerate(boxes) for b, q in boxes[i + 1:] if p.overlaps(q)]


@pytest.mark.parametrize("panels", [1, 2])
def test_labels_of_near_maxima_on_a_path_do_not_overlap(panels):
    s = 61
    path = np.column_stack([np.linspace(0.0, 1.48, s), np.zeros(s), np.zeros(s)])  # m
    bands = _bands(s, [0, 3, 0, s - 1, s - 1])
    fig = error_bands_figure(path, [(f"({k})", bands) for k in "ab"[:panels]])
    drawn, _ = _drawn(fig)
    for ax, texts in drawn:
        assert sorted(float(t) for t, _ in texts) == sorted(PEAKS_MM)
        assert _overlapping(texts) == []
        zero = ax.transData.transform((0.0, 0.0))[1]
        assert all(box.y0 > zero for _, box in texts)  # no label crosses the target line
        assert all(ax.get_window_extent().x0 - 1 <= box.x0 and box.x1 <= ax.get_window_extent().x1 + 1
                   for _, box in texts)  # a maximum at the end of the path labels to its left
        assert ax.get_legend() is None
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["Target trajectory"] + [b.label for b in bands]


def test_labels_of_poses_off_a_path_stand_above_every_bar_they_cross():
    s = 9
    holes = np.column_stack([np.repeat([0.6, 0.75, 0.9], 3), np.tile([-0.3, 0.0, 0.3], 3), np.zeros(s)])
    bands = _bands(s, [s - 1] * 5)  # every maximum in the last group
    fig = bands_figure(holes, bands, "one panel")
    drawn, renderer = _drawn(fig)
    (ax, texts), = drawn
    assert sorted(float(t) for t, _ in texts) == sorted(PEAKS_MM)
    assert _overlapping(texts) == []
    bars = [p.get_window_extent(renderer) for p in ax.patches]
    for text, box in texts:
        crossed = [b for b in bars if b.x0 < box.x1 and box.x0 < b.x1]
        assert crossed and box.y0 >= max(b.y1 for b in crossed) - 0.5, text
    # a label raised above other bars has a line down to its own bar's top; one just above it, none
    pt = fig.dpi / 72
    for t, (_, box) in zip(ax.texts, texts):
        raised = box.y0 - ax.transData.transform(t.xy)[1] > (3.0 + (LEADER_AFTER + 0.5) * 1.25 * PEAK_FONTSIZE) * pt
        assert (t.arrow_patch is not None) == raised, t.get_text()
    assert sum(t.arrow_patch is not None for t in ax.texts) == 4  # all but the highest, in one group
