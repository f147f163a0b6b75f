"""`rascal rddf plot`'s drawing (rascal/rddf_plot.py): a course that loops back over itself keeps
its labels apart, and its map keeps a metre as long east as north; the `rascal` command loads
matplotlib only to draw."""

from __future__ import annotations

import subprocess
import sys

from brain.corridor import Course
from rascal.rddf_plot import render_course
from tests.brain.rddf_samples import waypoints_at
from tests.conftest import ROOT
from tests.rascal.plot_checks import overlapping, text_boxes

# Out along the bottom, up, back over the start westwards, down and along the bottom again
# just beside the way out, finishing where it started: every corner is passed twice.
LOOP = [(0, 0), (100, 0), (100, 60), (-10, 60), (-10, 4), (104, 4), (104, 64), (4, 64), (4, 0), (0, 0)]


def test_labels_of_a_course_that_loops_back_do_not_collide() -> None:
    course = Course(waypoints_at(LOOP, offset_ft=8.0))
    figure = render_course(course, course.interpolate(), "loop.rddf", size_px=700)
    ax = figure.axes[0]
    labels = text_boxes(figure, ax)
    names = [name for name, _box in labels]
    assert "START" in names and "FINISH" in names
    assert len(names) >= 8, f"most waypoints keep a label: {names}"
    assert overlapping(labels) == [], "waypoint, start and finish labels stay apart"
    inside = ax.get_window_extent()
    assert all(inside.contains(box.x0, box.y0) and inside.contains(box.x1, box.y1) for _name, box in labels)
    assert overlapping(text_boxes(figure)) == [], "nor does any text of the figure cover another"
    assert ax.get_aspect() == 1.0


def test_the_rascal_command_loads_matplotlib_only_to_draw() -> None:
    # Every `rascal` command builds the whole parser; matplotlib would add half a second to each.
    code = "import sys; from rascal.cli import build_parser; build_parser(); print(sorted(sys.modules))"
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    loaded = result.stdout.split("'")
    assert "matplotlib" not in loaded and "rascal.rddf_plot" not in loaded and "rascal.plotting" not in loaded
