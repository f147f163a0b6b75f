"""Checks shared by the tests of the drawn images (rascal/plotting.py): the files are valid PNG
and SVG of a sensible size, no two texts of a figure overlap, and where data lands in the PNG."""

from __future__ import annotations

import io
import itertools
import xml.etree.ElementTree as ET
from pathlib import Path
from unittest.mock import patch

import cv2
import numpy as np
from matplotlib.axes import Axes
from matplotlib.backend_bases import RendererBase
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.text import Text
from matplotlib.transforms import Bbox

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SVG_TAG = "{http://www.w3.org/2000/svg}svg"


def assert_png(path: Path, max_side_px: int = 4000) -> np.ndarray:
    """The PNG as a BGR image, after checking it is one, of a sensible size and not blank."""
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path} is not a PNG"
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, f"{path} does not decode"
    assert 300 <= max(image.shape[:2]) <= max_side_px and min(image.shape[:2]) >= 150, image.shape
    assert len(np.unique(image.reshape(-1, 3)[::37], axis=0)) > 10, f"{path} is blank"
    return image


def assert_svg(path: Path) -> ET.Element:
    """The SVG's root after checking it parses as SVG, with a size and drawn content."""
    assert 2_000 < path.stat().st_size < 20_000_000, f"{path}: {path.stat().st_size} bytes"
    root = ET.parse(path).getroot()
    assert root.tag == SVG_TAG, root.tag
    width, height = (float(root.attrib[key].removesuffix("pt")) for key in ("width", "height"))
    assert width >= 100 and height >= 100
    assert root.find(".//{http://www.w3.org/2000/svg}path") is not None
    return root


def svg_texts(root: ET.Element) -> list[str]:
    """The SVG's text, as text (the figures keep their fonts out of the file)."""
    return ["".join(node.itertext()) for node in root.iter("{http://www.w3.org/2000/svg}text")]


def text_boxes(figure: Figure, ax: Axes | None = None) -> list[tuple[str, Bbox]]:
    """(text, pixel box) of every non-empty text a draw of the figure puts on the page (or of
    one axes' own labels). Only drawn texts count: an axis keeps labels of ticks outside its
    view, visible but never drawn, and a table's cells are not the figure's children."""
    drawn: list[Text] = []
    draw = Text.draw

    def record(text: Text, renderer: RendererBase) -> None:
        drawn.append(text)
        draw(text, renderer)

    with patch.object(Text, "draw", record):
        figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    own = set(ax.texts) if ax is not None else None
    return [
        (text.get_text(), text.get_window_extent(renderer))
        for text in drawn
        if text.get_visible() and text.get_text().strip() and (own is None or text in own)
    ]


def overlapping(boxes: list[tuple[str, Bbox]], tolerance_px: float = 0.5) -> list[tuple[str, str]]:
    """The pairs of texts whose boxes intersect by more than ``tolerance_px``."""
    shrunk = [(name, box.padded(-tolerance_px)) for name, box in boxes]
    return [(a, b) for (a, box_a), (b, box_b) in itertools.combinations(shrunk, 2) if box_a.overlaps(box_b)]


def png_of(figure: Figure) -> np.ndarray:
    """The figure as its PNG decodes (BGR), at the size it is written in."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=figure.dpi)
    return cv2.imdecode(np.frombuffer(buffer.getvalue(), np.uint8), cv2.IMREAD_COLOR)


def data_pixels(figure: Figure, ax: Axes, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(column, row) of the PNG's pixels that hold data points of ``ax`` (pixel k spans k to k + 1)."""
    display = ax.transData.transform(np.column_stack([np.ravel(x), np.ravel(y)]))
    height = figure.bbox.height
    return np.floor(np.column_stack([display[:, 0], height - display[:, 1]])).astype(int)


def bgr(colour: str | tuple[float, ...]) -> np.ndarray:
    """A matplotlib colour as the PNG's BGR integers."""
    r, g, b = to_rgb(colour)
    return np.round(np.array([b, g, r]) * 255).astype(int)
