"""Typed, named access to a TOML document, for files whose shape is written out by hand
(deployments, scenarios; a module's settings are checked from its config dataclass instead:
rascal.runtime.config). Every mistake is an error naming the file and the dotted key.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any


class TomlReader:
    """Readers of one document's values; ``error`` is the ValueError subclass they raise."""

    def __init__(self, path: Path, error: type[ValueError]) -> None:
        self.path = path
        self.error = error

    def fail(self, where: str, problem: str) -> ValueError:
        return self.error(f"{self.path}: {where}: {problem}" if where else f"{self.path}: {problem}")

    def keys(self, table: dict[str, Any], where: str, allowed: set[str]) -> None:
        unknown = sorted(set(table) - allowed)
        if unknown:
            raise self.fail(f"{where}.{unknown[0]}" if where else unknown[0], f"unknown key; known: {sorted(allowed)}")

    def table(self, doc: dict[str, Any], key: str, required: bool = False) -> dict[str, Any]:
        if key not in doc:
            if required:
                raise self.fail(key, "missing table")
            return {}
        found = doc[key]
        if not isinstance(found, dict):
            raise self.fail(key, "expected a table")
        return found

    def array(self, doc: dict[str, Any], key: str) -> list[dict[str, Any]]:
        found = doc.get(key, [])
        if not isinstance(found, list) or not all(isinstance(item, dict) for item in found):
            raise self.fail(key, f"expected an array of tables ([[{key}]])")
        return found

    def _value(self, table: dict[str, Any], where: str, key: str, default: Any) -> Any:
        if key in table:
            return table[key]
        if default is None:
            raise self.fail(f"{where}.{key}", "missing")
        return default

    def string(self, table: dict[str, Any], where: str, key: str, default: str | None = None) -> str:
        value = self._value(table, where, key, default)
        if not isinstance(value, str):
            raise self.fail(f"{where}.{key}", f"expected a string, got {value!r}")
        return value

    def integer(self, table: dict[str, Any], where: str, key: str, default: int | None = None) -> int:
        value = self._value(table, where, key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(f"{where}.{key}", f"expected an integer, got {value!r}")
        return value

    def number(
        self,
        table: dict[str, Any],
        where: str,
        key: str,
        default: float | None = None,
        low: float = -math.inf,
        high: float = math.inf,
    ) -> float:
        value = self._value(table, where, key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(f"{where}.{key}", f"expected a number, got {value!r}")
        if not low <= value <= high:
            raise self.fail(f"{where}.{key}", f"{value} is outside {low}..{high}")
        return float(value)

    def boolean(self, table: dict[str, Any], where: str, key: str, default: bool | None = None) -> bool:
        value = self._value(table, where, key, default)
        if not isinstance(value, bool):
            raise self.fail(f"{where}.{key}", f"expected true or false, got {value!r}")
        return value
