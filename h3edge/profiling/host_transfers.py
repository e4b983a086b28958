"""Counting a tensor's trips to the host: every call h3edge code makes that copies a torch tensor's
data to Python or numpy (``.cpu()``, ``.numpy()``, ``.item()``, ``.tolist()``, ``float()`` /
``int()`` / ``bool()`` of a tensor, ``np.asarray(tensor)``), by the source line that made it.

On CUDA each is a device-to-host copy and a pipeline stall; on a CPU the same calls are cheap, but
counting them there proves what a GPU run would do (issue [3/5]: the torch backend's training step
and integration should stay on the device). ``x.cpu().numpy()`` on one line counts once. Counted:
the calls h3edge makes itself (torch's own, e.g. an optimiser reading its CPU step counter, are
not).

Counted apart (``syncs``): the operators whose output size depends on the data, so that on CUDA
the host waits for the device to learn it, with no copy of the data itself: ``nonzero``,
``unique``, ``masked_select`` and indexing (reading or writing) with a boolean mask.

Counted apart too (``uploads``): host data made tensors (``torch.from_numpy``, ``torch.as_tensor``,
``torch.tensor`` of anything but a tensor) from h3edge code, in bytes by function: on CUDA each goes
up to the device (a copy from pageable memory: the host waits for the stream's work before it).

Usage::

    with HostTransfers() as ht:
        mapper.train_once()
    ht.total, ht.by_line()   # {"h3edge/mapping/trainer.py:128 cpu": 1, ...}
    ht.by_function()         # {"h3edge/mapping/cell_votes.py:sample_free": 3, ...}
    ht.syncs, ht.syncs_by_function()   # the data-dependent shapes, apart
    ht.uploads_by_function()           # {"h3edge/mapping/device_frames.py:_tensor": 921600, ...} bytes
"""

from __future__ import annotations

import collections
import sys
import threading
from pathlib import Path

import numpy as np
import torch

_PACKAGE = str(Path(__file__).resolve().parents[1])  # .../h3edge
_THIS = str(Path(__file__).resolve())
_METHODS = ("cpu", "numpy", "item", "tolist", "__float__", "__int__", "__bool__", "__array__")
_SYNC_METHODS = ("nonzero", "unique", "masked_select")  # Tensor methods and torch functions alike


def _bool_index(index) -> bool:
    """Whether an index (a tensor, or a tuple of indices) holds a boolean tensor."""
    items = index if isinstance(index, tuple) else (index,)
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in items)


class HostTransfers:
    """A context manager that counts host transfers of torch tensors made from h3edge code while it
    is open (one thread or many). Not re-entrant; patches ``torch.Tensor`` methods for its span."""

    def __init__(self):
        self.events: collections.Counter[tuple[str, str]] = collections.Counter()  # ("path:line", kind) -> count
        self.functions: collections.Counter[str] = collections.Counter()  # "path:function" -> count
        self._saved: dict[tuple[object, str], object] = {}
        self.sync_functions: collections.Counter[str] = collections.Counter()  # "path:function" -> syncs
        self._last: dict[int, tuple[str, str]] = {}  # thread id -> the last (site, kind): cpu then numpy
        self.upload_functions: collections.Counter[str] = collections.Counter()  # "path:function" -> bytes

    @property
    def total(self) -> int:
        """Host transfers counted so far."""
        return sum(self.events.values())

    def by_line(self) -> dict[str, int]:
        """``"path:line kind"`` (path relative to the repository) -> count, largest first."""
        return {f"{site} {kind}": n for (site, kind), n in self.events.most_common()}

    @property
    def syncs(self) -> int:
        """Data-dependent shapes counted so far (module docstring)."""
        return sum(self.sync_functions.values())

    def syncs_by_function(self) -> dict[str, int]:
        """``"path:function"`` -> syncs, largest first."""
        return dict(self.sync_functions.most_common())

    def uploads_by_function(self) -> dict[str, int]:
        """``"path:function"`` -> bytes of host arrays made tensors there (module docstring), largest first."""
        return dict(self.upload_functions.most_common())

    def by_function(self) -> dict[str, int]:
        """``"path:function"`` -> count, largest first (stable across edits that move lines)."""
        return dict(self.functions.most_common())

    @staticmethod
    def _site() -> tuple[str, str] | None:
        frame = sys._getframe(3)  # _site <- _record(_sync) <- the patched method <- its caller
        path = frame.f_code.co_filename
        if not path.startswith(_PACKAGE) or path == _THIS:
            return None
        rel = Path(path).relative_to(Path(_PACKAGE).parent)
        return f"{rel}:{frame.f_lineno}", f"{rel}:{frame.f_code.co_name}"

    def _record(self, kind: str) -> None:
        where = self._site()
        if where is None:  # torch's or a test's own call
            return
        site, function = where
        tid = threading.get_ident()
        if kind == "numpy" and self._last.get(tid) == (site, "cpu"):
            self._last[tid] = (site, kind)
            return  # x.cpu().numpy(): one transfer
        self._last[tid] = (site, kind)
        self.events[(site, kind.strip("_"))] += 1
        self.functions[function] += 1

    def _record_sync(self) -> None:
        where = self._site()
        if where is not None:
            self.sync_functions[where[1]] += 1

    def _record_upload(self, data: object) -> None:
        where = self._site()
        if where is not None and not isinstance(data, torch.Tensor):
            try:
                self.upload_functions[where[1]] += np.asarray(data).nbytes
            except (TypeError, ValueError):
                self.upload_functions[where[1]] += 1

    def _patch(self, owner: object, name: str, wrapper_of) -> None:
        original = getattr(owner, name)
        self._saved[(owner, name)] = original
        setattr(owner, name, wrapper_of(original))

    def __enter__(self) -> HostTransfers:
        for name in _METHODS:
            def transfer(original, _name=name):
                def wrapper(t, *args, **kwargs):
                    self._record(_name)
                    return original(t, *args, **kwargs)
                return wrapper
            self._patch(torch.Tensor, name, transfer)

        def sync(original):
            def wrapper(*args, **kwargs):
                self._record_sync()
                return original(*args, **kwargs)
            return wrapper

        def sync_if_bool(original):
            def wrapper(t, index, *args):
                if _bool_index(index):
                    self._record_sync()
                return original(t, index, *args)
            return wrapper

        for name in _SYNC_METHODS:
            self._patch(torch.Tensor, name, sync)
            self._patch(torch, name, sync)
        def upload(original):
            def wrapper(data, *args, **kwargs):
                self._record_upload(data)
                return original(data, *args, **kwargs)
            return wrapper

        for name in ("from_numpy", "as_tensor", "tensor"):
            self._patch(torch, name, upload)
        self._patch(torch.Tensor, "__getitem__", sync_if_bool)
        self._patch(torch.Tensor, "__setitem__", sync_if_bool)
        return self

    def __exit__(self, *exc) -> None:
        for (owner, name), original in self._saved.items():
            setattr(owner, name, original)
        self._saved.clear()
