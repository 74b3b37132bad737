"""Markdown pieces of the report: a section's lines and pictures, tables, and cells
formatted with their bounds."""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["Section", "bounded", "fmt", "table", "upper"]


@dataclass(frozen=True)
class Section:
    """A part of the report: its Markdown lines and the pictures they reference."""

    lines: list[str]
    pictures: list[Path] = field(default_factory=list)


def fmt(value: Any, digits: int = 1, unit: str = "") -> str:
    """A cell's text: ``-`` for a missing or non-finite value, a time to the second, a float
    to ``digits`` decimals."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, dt.datetime):
        return value.strftime("%Y-%m-%d %H:%M:%S")
    if isinstance(value, float):
        return f"{value:.{digits}f}{unit}"
    return f"{value}{unit}"


def _cell(value: Any) -> str:
    return str(value).replace("|", "\\|").replace("\n", " ")


def table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    """A Markdown table, and the blank line after it."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    lines.append("")
    return lines


def bounded(value: Any, lo: Any, hi: Any, digits: int = 1) -> str:
    """A value with its 95 % bounds: ``412.3 (398.1 to 426.5)``; ``-`` without a value."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{fmt(value, digits)} ({fmt(lo, digits)} to {fmt(hi, digits)})"


def upper(value: Any, hi: Any, digits: int = 1) -> str:
    """A value with its 95 % upper bound: ``430.2 (≤ 441.0)``."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{fmt(value, digits)} (≤ {fmt(hi, digits)})"
