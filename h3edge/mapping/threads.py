"""The mapper's CPU threads: how many its pools use and which of its own threads goes first.

Two rules, both from the mapper's settings (``[mapper] threads``, ``[mapper] training_nice``):

- Pool sizes (:func:`size_pools`): torch's intra-op pool and numba's parallel kernels launched from
  the calling thread use ``threads`` threads (0: leave them as they are, every core). On a robot the
  mapper shares the CPU with perception and planning; pools sized to every core, whose workers wait
  for each other at every parallel region, stall whenever one of them loses its core. onnxruntime's
  decoders take their own ``onnx.threads``.
- Integration before training (:func:`lower_thread_priority`): the background training thread runs
  ``training_nice`` nice levels below the thread that integrates (Linux: nice is per thread, and the
  OpenMP workers a thread's first parallel region starts inherit it), so that when both want a
  core, integration (one frame each camera period) gets it and training takes the rest. Within the
  process only: with autogroup or the service's cgroup the process as a whole still competes with
  the rest of the robot for its fair share.

Spinning: OpenMP workers that spin after a parallel region burn the cores another thread (the other
pool, another process) needs. ``OMP_WAIT_POLICY=PASSIVE`` must be in the environment before torch
is imported (the OpenMP runtime reads it once, when it loads): the service's unit file and the CLI
set it (:data:`PASSIVE_ENVIRONMENT`); a library user sets it in their own environment.
"""

from __future__ import annotations

import logging
import os
import threading

log = logging.getLogger(__name__)

# what the service and the CLI put in the environment before torch loads (a user's own value wins)
PASSIVE_ENVIRONMENT = {"OMP_WAIT_POLICY": "PASSIVE", "KMP_BLOCKTIME": "0"}


def passive_environment(environ: dict | None = None) -> None:
    """Set :data:`PASSIVE_ENVIRONMENT` in ``environ`` (default ``os.environ``) where not set. Takes
    effect only if called before torch (and numba's OpenMP layer) are loaded."""
    env = os.environ if environ is None else environ
    for key, value in PASSIVE_ENVIRONMENT.items():
        env.setdefault(key, value)


def size_pools(threads: int) -> None:
    """torch's intra-op threads (process-wide) and numba's threads for parallel kernels launched
    from the calling thread (numba's setting is per thread) to ``threads``, capped at numba's pool
    (``NUMBA_NUM_THREADS``, the cores); 0 leaves both as they are."""
    if threads <= 0:
        return
    import numba
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def lower_thread_priority(increment: int) -> int:
    """Raise the calling thread's nice value by ``increment`` (0..19; Linux, where nice is per
    thread: threads it starts afterwards inherit it). Returns the nice value now; on other systems,
    or where refused, logs and leaves it."""
    if increment <= 0 or not hasattr(os, "setpriority"):
        return 0
    tid = threading.get_native_id()
    try:
        nice = min(19, os.getpriority(os.PRIO_PROCESS, tid) + increment)
        os.setpriority(os.PRIO_PROCESS, tid, nice)
        return nice
    except OSError as e:
        log.warning("could not lower the training thread's priority: %s", e)
        return 0
