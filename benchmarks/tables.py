"""Shared benchmark helpers: markdown tables (a column is (header, value of a row, decimals)), written
as OUT.md + OUT.json, and median wall-clock timings."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

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


def write_table(out: str | Path, title: str, columns: list[Column], rows: list[dict]) -> str:
    """Print the markdown table and write it as OUT.md, with ``{"title", "rows"}`` as OUT.json."""
    table = markdown_table(title, columns, rows)
    print(table, flush=True)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"title": title, "rows": rows}, indent=1) + "\n")
    out.with_suffix(".md").write_text(table + "\n")
    return table
