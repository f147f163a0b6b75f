"""Line charts drawn with OpenCV for the run report: a frame with ticked, labelled axes, lines
(NaN breaks them), shaded bands, markers and a legend. The text, colours and tick steps are
the RDDF plot's (brain/rddf_cli.py), so the report's pictures look like one family."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike

from brain.rddf_cli import FONT, INK, PAPER, SHIFT, Color, draw_text, nice_length, to_point

GRID: Color = (232, 232, 232)
LEFT_PX, RIGHT_PX, TOP_PX, BOTTOM_PX = 90, 30, 56, 62  # room for labels around the plot area
SWATCH_PX = 28
ROW_PX = 20


@dataclass
class LegendEntry:
    label: str
    color: Color
    thickness: int = 2  # a line's thickness, a marker's radius
    kind: str = "line"  # "line", "band" or "marker"


def legend_size(entries: list[LegendEntry], scale: float = 0.45) -> tuple[int, int]:
    """Width and height of the legend box of ``entries``."""
    text_w = max(cv2.getTextSize(entry.label, FONT, scale, 1)[0][0] for entry in entries)
    return SWATCH_PX + 18 + text_w, ROW_PX * len(entries) + 10


def draw_legend(image: np.ndarray, entries: list[LegendEntry], x0: int, y0: int, scale: float = 0.45) -> None:
    """A boxed legend with its top-left corner at (x0, y0): a swatch and a label per entry."""
    box_w, box_h = legend_size(entries, scale)
    cv2.rectangle(image, (x0, y0), (x0 + box_w, y0 + box_h), PAPER, -1)
    cv2.rectangle(image, (x0, y0), (x0 + box_w, y0 + box_h), INK, 1)
    for row, entry in enumerate(entries):
        y = y0 + 15 + row * ROW_PX
        a, b = (x0 + 6, y), (x0 + 6 + SWATCH_PX, y)
        if entry.kind == "line":
            cv2.line(image, a, b, entry.color, max(entry.thickness, 2), cv2.LINE_AA)
        elif entry.kind == "band":
            cv2.rectangle(image, (a[0], y - 6), (b[0], y + 6), entry.color, -1)
            cv2.rectangle(image, (a[0], y - 6), (b[0], y + 6), INK, 1)
        else:
            centre = ((a[0] + b[0]) // 2, y)
            cv2.circle(image, centre, entry.thickness, entry.color, -1, cv2.LINE_AA)
            cv2.circle(image, centre, entry.thickness, INK, 1, cv2.LINE_AA)
        draw_text(image, entry.label, np.array([b[0] + 10.0, y + 5.0]), scale)


@dataclass
class Chart:
    """One x-y plot in ``box`` (left, top, width, height: the whole panel, labels included)."""

    image: np.ndarray
    box: tuple[int, int, int, int]
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    title: str
    x_label: str
    y_label: str
    log_x: bool = False
    left_px: int = LEFT_PX  # room for the y tick labels (categories need more)
    y_labels: list[str] | None = None  # categorical y: label i names the row from y = n-1-i to n-i
    legend: list[LegendEntry] = field(default_factory=list)

    def __post_init__(self) -> None:
        left, top, width, height = self.box
        self.plot = (left + self.left_px, top + TOP_PX, width - self.left_px - RIGHT_PX, height - TOP_PX - BOTTOM_PX)
        low, high = self.x_range
        if self.log_x:
            low, high = math.log10(low), math.log10(high)
        self._x = (low, high if high > low else low + 1.0)
        low, high = self.y_range
        self._y = (low, high if high > low else low + 1.0)
        self._draw_frame()

    # -- coordinates --------------------------------------------------------------------------

    def px(self, x: ArrayLike, y: ArrayLike) -> np.ndarray:
        """Pixel positions (float) of data points; values outside the ranges land outside the plot."""
        left, top, width, height = self.plot
        x = np.asarray(x, dtype=float)
        if self.log_x:
            x = np.log10(np.maximum(x, 1e-12))
        fx = (x - self._x[0]) / (self._x[1] - self._x[0])
        fy = (np.asarray(y, dtype=float) - self._y[0]) / (self._y[1] - self._y[0])
        return np.stack(np.broadcast_arrays(left + fx * width, top + (1.0 - fy) * height), axis=-1)

    # -- drawing --------------------------------------------------------------------------------

    def line(self, x: ArrayLike, y: ArrayLike, color: Color, label: str = "", thickness: int = 2) -> None:
        """A polyline through the points in order; a NaN in ``y`` (or ``x``) leaves a gap."""
        points = self.px(x, y)
        finite = np.all(np.isfinite(points), axis=-1)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], finite.astype(np.int8), [0]])))
        clip = self._clipped()
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            run = np.round(points[start:stop] * (1 << SHIFT)).astype(np.int32)
            cv2.polylines(clip, [run], False, color, thickness, cv2.LINE_AA, SHIFT)
        self._paste(clip)
        if label:
            self.legend.append(LegendEntry(label, color, thickness, "line"))

    def band(self, x: ArrayLike, low: ArrayLike, high: ArrayLike, color: Color, label: str = "") -> None:
        """The area between ``low`` and ``high`` over ``x``, filled."""
        upper = self.px(x, high)
        lower = self.px(x, low)[::-1]
        polygon = np.round(np.concatenate([upper, lower]) * (1 << SHIFT)).astype(np.int32)
        clip = self._clipped()
        cv2.fillPoly(clip, [polygon], color, cv2.LINE_AA, SHIFT)
        self._paste(clip)
        if label:
            self.legend.append(LegendEntry(label, color, 0, "band"))

    def markers(self, x: ArrayLike, y: ArrayLike, color: Color, label: str = "", radius: int = 5) -> None:
        for point in self.px(x, y).reshape(-1, 2):
            if self._inside(point):
                cv2.circle(self.image, to_point(point), radius, color, -1, cv2.LINE_AA)
                cv2.circle(self.image, to_point(point), radius, INK, 1, cv2.LINE_AA)
        if label:
            self.legend.append(LegendEntry(label, color, radius, "marker"))

    def spans(self, x: ArrayLike, low: ArrayLike, high: ArrayLike, color: Color, label: str = "") -> None:
        """A thick vertical bar from ``low`` to ``high`` at each ``x`` (e.g. an obstacle's width)."""
        clip = self._clipped()
        for bottom, top in zip(self.px(x, low).reshape(-1, 2), self.px(x, high).reshape(-1, 2), strict=True):
            cv2.line(clip, to_point(bottom), to_point(top), color, 6, cv2.LINE_AA)
        self._paste(clip)
        if label:
            self.legend.append(LegendEntry(label, color, 6))

    def note(self, text: str) -> None:
        """A line of text under the title (what the numbers say, e.g. RMS and max)."""
        left, top, _width, _height = self.box
        draw_text(self.image, text, np.array([left + self.left_px, top + 46.0]), 0.45)

    def draw_legend(self, corner: str = "top right") -> None:
        """The legend inside the plot, in one corner (``top``/``bottom`` + ``left``/``right``), or
        ``above`` it, right of the title."""
        if not self.legend:
            return
        left, top, width, height = self.plot
        box_w, box_h = legend_size(self.legend)
        x0 = left + width - box_w - 10 if "right" in corner or corner == "above" else left + 10
        y0 = top + 10 if "top" in corner else top + height - box_h - 10
        if corner == "above":
            y0 = max(0, top - box_h - 4)
        draw_legend(self.image, self.legend, x0, y0)

    # -- internals ------------------------------------------------------------------------------

    def _draw_frame(self) -> None:
        left, top, width, height = self.plot
        for x in self._ticks(self._x, log=self.log_x):
            (px, _), label = self.px(x, self._y[0]), _tick_label(x)
            cv2.line(self.image, to_point([px, top]), to_point([px, top + height]), GRID, 1)
            cv2.line(self.image, to_point([px, top + height]), to_point([px, top + height + 5]), INK, 1)
            text_w = cv2.getTextSize(label, FONT, 0.45, 1)[0][0]
            draw_text(self.image, label, np.array([px - text_w / 2.0, top + height + 22.0]), 0.45)
        x_min = 10 ** self._x[0] if self.log_x else self._x[0]
        if self.y_labels is not None:  # categories: a label per row, a grid line between rows
            rows = len(self.y_labels)
            for index, label in enumerate(self.y_labels):
                (_, py), (_, line_y) = self.px(x_min, rows - index - 0.5), self.px(x_min, rows - index - 1)
                cv2.line(self.image, to_point([left, line_y]), to_point([left + width, line_y]), GRID, 1)
                text_w = cv2.getTextSize(label, FONT, 0.45, 1)[0][0]
                draw_text(self.image, label, np.array([left - 10.0 - text_w, py + 5.0]), 0.45)
        for y in self._ticks(self._y) if self.y_labels is None else []:
            (_, py), label = self.px(x_min, y), _tick_label(y)
            cv2.line(self.image, to_point([left, py]), to_point([left + width, py]), GRID, 1)
            cv2.line(self.image, to_point([left - 5, py]), to_point([left, py]), INK, 1)
            text_w = cv2.getTextSize(label, FONT, 0.45, 1)[0][0]
            draw_text(self.image, label, np.array([left - 10.0 - text_w, py + 5.0]), 0.45)
        cv2.rectangle(self.image, (left, top), (left + width, top + height), INK, 1)
        box_left, box_top, _box_w, box_h = self.box
        draw_text(self.image, self.title, np.array([box_left + self.left_px, box_top + 24.0]), 0.65)
        x_w = cv2.getTextSize(self.x_label, FONT, 0.5, 1)[0][0]
        draw_text(self.image, self.x_label, np.array([left + (width - x_w) / 2.0, box_top + box_h - 12.0]), 0.5)
        if self.y_label:
            self._vertical_label(self.y_label, box_left + 8, top + height // 2)

    @staticmethod
    def _ticks(limits: tuple[float, float], log: bool = False) -> list[float]:
        low, high = limits
        if log:
            return [10.0**k for k in range(math.ceil(low), math.floor(high) + 1)]
        step = nice_length((high - low) / 5.0)
        first = math.ceil(low / step - 1e-9) * step
        return [first + k * step for k in range(int((high - first) / step + 1e-9) + 1)]

    def _vertical_label(self, text: str, x: int, centre_y: int) -> None:
        (text_w, text_h), _ = cv2.getTextSize(text, FONT, 0.5, 1)
        strip = np.full((text_h + 10, text_w + 6, 3), PAPER, dtype=np.uint8)
        cv2.putText(strip, text, (3, text_h + 3), FONT, 0.5, INK, 1, cv2.LINE_AA)
        rotated = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
        y0 = max(0, centre_y - rotated.shape[0] // 2)
        rows = min(rotated.shape[0], self.image.shape[0] - y0)
        self.image[y0 : y0 + rows, x : x + rotated.shape[1]] = rotated[:rows]

    def _clipped(self) -> np.ndarray:
        """A copy of the image to draw on, so strokes outside the plot area can be cut off."""
        return self.image.copy()

    def _paste(self, drawn: np.ndarray) -> None:
        left, top, width, height = self.plot
        inside = np.s_[top + 1 : top + height, left + 1 : left + width]
        self.image[inside] = drawn[inside]

    def _inside(self, point: np.ndarray) -> bool:
        left, top, width, height = self.plot
        return bool(np.all(np.isfinite(point))) and left <= point[0] <= left + width and top <= point[1] <= top + height


def _tick_label(value: float) -> str:
    if value != 0 and (abs(value) >= 1e5 or abs(value) < 1e-3):
        return f"{value:.0e}"
    return f"{value:.10g}" if abs(value - round(value)) > 1e-9 else f"{round(value)}"
