"""Shared benchmark helpers: markdown tables (a column is (header, value of a row, decimals)) and
median wall-clock timings."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

Column = tuple[str, Callable[[dict], object], "int | None"]


def cell(v, decimals: int | None = 2) -> str:
    """A number to ``decimals`` places ("—" when missing); ``decimals=None`` prints it as it is."""
    if v is None:
        return "—"
    return str(v) if decimals is None else f"{v:.{decimals}f}"


def markdown_table(title: str, columns: list[Column], rows: list[dict]) -> str:
    out = [f"### {title}", "", "| " + " | ".join(h for h, _, _ in columns) + " |", "|---" * len(columns) + "|"]
    out += ["| " + " | ".join(cell(get(r), p) for _, get, p in columns) + " |" for r in rows]
    return "\n".join(out)


def median_time(fn: Callable[[], object], repeats: int, warmup: bool = True) -> float:
    """Median seconds of ``repeats`` calls of ``fn``, after one untimed call (JIT, allocator)."""
    if warmup:
        fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))
