"""Result tables: rich on a terminal, plain aligned text when piped (logs, CI, ``| tee``)."""

from __future__ import annotations

import os
import platform
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console
from rich.table import Table as RichTable


@dataclass
class Table:
    """A titled grid of preformatted cells; the first column is a label, the rest are numbers."""

    title: str
    columns: list[str]
    rows: list[list[str]] = field(default_factory=list)

    def add(self, *cells: str) -> None:
        if len(cells) != len(self.columns):
            raise ValueError(f"{self.title}: {len(cells)} cells for {len(self.columns)} columns")
        self.rows.append(list(cells))


def print_table(console: Console, table: Table) -> None:
    if console.is_terminal:
        console.print(_rich(table))
        console.print()
    else:
        # Plain text on purpose: box-drawing characters and wrapping make piped logs hard to diff.
        console.print(_plain(table), markup=False, highlight=False, soft_wrap=True)


def _rich(table: Table) -> RichTable:
    out = RichTable(title=table.title, title_justify="left")
    for index, name in enumerate(table.columns):
        out.add_column(name, justify="left" if index == 0 else "right")
    for row in table.rows:
        out.add_row(*row)
    return out


def _plain(table: Table) -> str:
    grid = [table.columns, *table.rows]
    widths = [max(len(row[i]) for row in grid) for i in range(len(table.columns))]

    def line(row: list[str]) -> str:
        cells = [row[0].ljust(widths[0])] + [cell.rjust(width) for cell, width in zip(row[1:], widths[1:], strict=True)]
        return "  ".join(cells).rstrip()

    rule = "-" * len(line(table.columns))
    return "\n".join([table.title, line(table.columns), rule, *map(line, table.rows), ""])


def machine_line(benchmark: str, where: str = "") -> str:
    """One header line naming the machine; load from other work skews every row, so say how much."""
    cores = os.cpu_count() or 0
    usable = len(os.sched_getaffinity(0))
    parts = [
        f"{benchmark} benchmark",
        f"Python {platform.python_version()}",
        f"{cores} cores ({usable} usable)",
        _cpu_model(),
        f"{platform.system()} {platform.release()}",
        f"load {os.getloadavg()[0]:.2f} at start",
    ]
    return " | ".join([*parts, where] if where else parts)


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"
