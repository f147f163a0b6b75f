"""``python -m benchmarks``: run every benchmark module in turn (each has ``main() -> int``)."""

from __future__ import annotations

import importlib
import sys

# Add new benchmark modules here; they run in this order.
MODULES = [
    "benchmarks.bench_bus",
    "benchmarks.bench_sim",
    "benchmarks.bench_lidar",
    "benchmarks.bench_ins",
    "benchmarks.bench_camera",
    "benchmarks.bench_fusion",
    "benchmarks.bench_vision",
    "benchmarks.bench_planner",
    "benchmarks.bench_cambada",
]


def main() -> int:
    status = 0
    for name in MODULES:
        status = max(status, importlib.import_module(name).main([]))
    return status


if __name__ == "__main__":
    sys.exit(main())
