"""Which implementation runs the per-message hot path: the C extension, or its Python twin.

``protocol/_fastpath.c`` tags, seals, opens, decodes and replay-checks the common case (a
well-formed, authentic message of this build's layout) and hands everything else back to the
Python code in auth.py, codec.py, schema.py, replay.py and rascal/runtime/bus.py, which stays the
reference; except a wrong tag, which C refuses itself (bad_mac), so that no datagram's tag is
computed twice. ``native`` is that extension, or None where it was not
built (no compiler at install time), is a stale build, or ``RASCAL_PURE_PYTHON=1`` asks for
Python (the tests run both ways).
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType

# Must equal FASTPATH_ABI in _fastpath.c: a build from older sources is not used.
ABI = 6
PURE_PYTHON_ENV = "RASCAL_PURE_PYTHON"


def pure_python_asked() -> bool:
    return os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0")


def _load() -> ModuleType | None:
    if pure_python_asked():
        return None
    try:
        _fastpath = importlib.import_module("protocol._fastpath")
    except ImportError:
        return None
    return _fastpath if getattr(_fastpath, "ABI", None) == ABI else None


native = _load()


def describe() -> str:
    """One line for status output and benchmark headers."""
    if native is not None:
        return "C fast path"
    if pure_python_asked():
        return f"pure Python ({PURE_PYTHON_ENV} set)"
    return "pure Python (C fast path not built)"
