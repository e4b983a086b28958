"""Markdown tables for the benchmark reports: a column is (header, value of a row, decimals)."""

from __future__ import annotations

from typing import Callable

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
