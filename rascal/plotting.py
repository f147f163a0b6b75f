"""The one place the tools draw: matplotlib figures for the run report (rascal/report*.py) and
`rascal rddf plot` (rascal/rddf_plot.py). Figures are made without pyplot (no display, no global
state: Agg renders them), written as PNG and SVG, and their text labels are kept apart by
`LabelPlacer`."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

import matplotlib as mpl
import numpy as np
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Colormap, Normalize
from matplotlib.figure import Figure
from matplotlib.layout_engine import ConstrainedLayoutEngine
from matplotlib.legend import Legend
from matplotlib.text import Annotation
from matplotlib.transforms import Bbox

from brain.corridor import MPH_TO_MPS

P = ParamSpec("P")
R = TypeVar("R")
DPI = 100  # figure sizes below are in pixels at this resolution
FORMATS = ("png", "svg")
INK = "#282828"
PAPER = "#ffffff"
CORRIDOR_FILL = "#d6e2ec"
CORRIDOR_EDGE = "#8296aa"
SPEED_CMAP: Colormap = mpl.colormaps["turbo"]
# Text stays readable over lines and fills. A box, not a halo: a path effect turns the SVG's
# text into outlines.
LABEL_BOX = {"boxstyle": "square,pad=0.15", "facecolor": PAPER, "edgecolor": "none", "alpha": 0.8}
STYLE = {
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "legend.fontsize": 9,
    "axes.grid": True,
    "grid.color": "#e6e6e6",
    "axes.axisbelow": True,
    "svg.fonttype": "none",  # SVG text stays text: small files, searchable labels
    "svg.hashsalt": "rascal",  # the same drawing gives the same SVG
}


def styled(render: Callable[P, R]) -> Callable[P, R]:
    """Draw in the house style: matplotlib reads its settings when each artist is made, so the
    whole of a figure's drawing runs inside it (without changing them for the process)."""

    @functools.wraps(render)
    def draw(*args: P.args, **kwargs: P.kwargs) -> R:
        with style():
            return render(*args, **kwargs)

    return draw


def style() -> AbstractContextManager[None]:
    return mpl.rc_context(STYLE)


def new_figure(width_px: float, height_px: float) -> Figure:
    """A figure of this many pixels (PNG, rounded) with constrained layout and an Agg canvas."""
    figure = Figure(figsize=(round(width_px) / DPI, round(height_px) / DPI), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def freeze_layout(figure: Figure) -> None:
    """Lay the figure out and keep it: pixel positions (labels placed by `LabelPlacer`, tests
    that look at the PNG) stay what they are when it is saved, and saving it as PNG and SVG
    lays it out once, not once per format."""
    with style():
        figure.draw_without_rendering()
    figure.set_layout_engine("none")


def pin_legend(legend: Legend, ax: Axes) -> None:
    """Keep a legend placed "best" where the layout put it: labels added later would otherwise
    move it when the figure is drawn again (the best place avoids texts too)."""
    placed = legend.get_window_extent().transformed(ax.transAxes.inverted())
    legend.set_loc("center")
    legend.set_bbox_to_anchor(placed)


def save_figure(figure: Figure, stem: Path, formats: Iterable[str] = FORMATS) -> list[Path]:
    """Write ``stem.png`` and ``stem.svg`` (or the given formats); returns the files."""
    if isinstance(figure.get_layout_engine(), ConstrainedLayoutEngine):
        freeze_layout(figure)
    written = []
    for fmt in formats:
        path = stem.with_name(f"{stem.name}.{fmt}")
        save_as(figure, path)
        written.append(path)
    return written


def save_as(figure: Figure, path: Path) -> None:
    """Write the figure in the format its file name says (png, svg, pdf); OSError or ValueError."""
    # No timestamps or software versions in the files: the same drawing gives the same bytes.
    metadata = {"Software": None} if path.suffix.lower() == ".png" else {"Date": None, "Creator": None}
    with style():
        figure.savefig(path, dpi=DPI, metadata=metadata, facecolor=PAPER)


def speed_norm(vmax_mps: float) -> Normalize:
    return Normalize(0.0, max(vmax_mps, 1e-6))


def speed_colorbar(figure: Figure, ax: Axes, mappable: mpl.cm.ScalarMappable, label: str) -> None:
    """A horizontal colour bar under the map in m/s, with mph on its top edge."""
    bar = figure.colorbar(
        mappable, ax=ax, orientation="horizontal", location="bottom", fraction=0.035, aspect=50, pad=0.02
    )
    bar.set_label(f"{label} (m/s)")
    mph = bar.ax.secondary_xaxis("top", functions=(lambda v: v / MPH_TO_MPS, lambda v: v * MPH_TO_MPS))
    mph.set_xlabel("mph", fontsize=8, labelpad=4)
    mph.tick_params(labelsize=8)


class LabelPlacer:
    """Puts text labels beside points so that no two overlap: each label tries positions around
    its point, nearest first, and takes the first that is free and inside the axes; a label with
    no free place is left out (a course that loops back keeps one label where several would
    pile up). Call once the layout is frozen (`freeze_layout`): it measures in pixels."""

    GAP_PX = 4.0
    PAD_PX = 2.0  # the label's box reaches this far past its text

    def __init__(self, ax: Axes) -> None:
        self.ax = ax
        self.taken: list[Bbox] = []
        self._renderer = ax.figure.canvas.get_renderer()

    def avoid(self, xy_data: np.ndarray, radius_px: float) -> None:
        """Keep labels off a marker at this place."""
        for x, y in self.ax.transData.transform(np.reshape(xy_data, (-1, 2))):
            self.taken.append(Bbox.from_extents(x - radius_px, y - radius_px, x + radius_px, y + radius_px))

    def avoid_artist(self, artist: Artist) -> None:
        """Keep labels off an artist already drawn (a legend)."""
        self.taken.append(artist.get_window_extent(self._renderer))

    def place(
        self, xy_data: tuple[float, float], text: str, clear_px: float = 0.0, **text_style: Any
    ) -> Annotation | None:
        """The label of a point (``clear_px``: the radius of its marker), or None when it has no room."""
        label = self.ax.annotate(
            text,
            xy_data,
            xytext=(0, 0),
            textcoords="offset points",
            ha="left",
            va="bottom",
            bbox=LABEL_BOX,
            **text_style,
        )
        box = label.get_window_extent(self._renderer)
        anchor = self.ax.transData.transform(xy_data)
        for dx, dy in self._offsets(box.width, box.height, clear_px + self.GAP_PX):
            candidate = Bbox.from_bounds(anchor[0] + dx, anchor[1] + dy, box.width, box.height)
            if self._free(candidate):
                # In points, not pixels: the SVG backend renders at 72 dpi.
                shift = (dx - (box.x0 - anchor[0]), dy - (box.y0 - anchor[1]))
                label.xyann = (shift[0] * 72.0 / DPI, shift[1] * 72.0 / DPI)
                self.taken.append(candidate)
                return label
        label.remove()
        return None

    @staticmethod
    def _offsets(width: float, height: float, gap: float) -> list[tuple[float, float]]:
        """Lower-left corners relative to the point: the four diagonals, then the sides, then
        the same twice as far out."""
        rings = []
        for reach in (gap, 2.5 * gap):
            rings += [
                (reach, reach),
                (-width - reach, reach),
                (reach, -height - reach),
                (-width - reach, -height - reach),
                (reach, -height / 2.0),
                (-width - reach, -height / 2.0),
                (-width / 2.0, reach),
                (-width / 2.0, -height - reach),
            ]
        return rings

    def _free(self, box: Bbox) -> bool:
        inner = self.ax.get_window_extent(self._renderer)
        if not (inner.x0 <= box.x0 and box.x1 <= inner.x1 and inner.y0 <= box.y0 and box.y1 <= inner.y1):
            return False
        padded = box.padded(self.PAD_PX)
        return not any(padded.overlaps(other) for other in self.taken)
