"""Progress bars for long commands (``h3edge map``, ``sim make``, ``eval``): a tqdm bar on a
terminal, nothing otherwise (logs and CI keep their plain log lines)."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


def on_terminal() -> bool:
    """True when standard error is an interactive terminal (where a bar redraws in place)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # closed or replaced stream
        return False


def progress(items: Iterable[T], total: int | None = None, desc: str = "", unit: str = "frame") -> Iterator[T]:
    """``items`` with a progress bar on a terminal (tqdm, on standard error); the items alone
    elsewhere."""
    if not on_terminal():
        yield from items
        return
    from tqdm import tqdm

    with tqdm(items, total=total, desc=desc, unit=unit, leave=False, dynamic_ncols=True) as bar:
        yield from bar


class ProgressBar:
    """A bar advanced by hand (``update(n)``), for loops that are not a plain iteration (a live
    replay skips frames); a no-op off a terminal. Use as a context manager."""

    def __init__(self, total: int, desc: str = "", unit: str = "frame"):
        self._bar = None
        if on_terminal():
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=desc, unit=unit, leave=False, dynamic_ncols=True)

    def update(self, n: int = 1, **postfix) -> None:
        """Advance by ``n``; ``postfix`` values show after the bar (e.g. voxels=1234)."""
        if self._bar is not None:
            if postfix:
                self._bar.set_postfix(postfix, refresh=False)
            self._bar.update(n)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
