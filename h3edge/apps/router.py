"""``h3edge router``: a zenoh router for a site's fleet, in this Python install (no ``zenohd`` needed).

A zenoh session opened in router mode routes between every client and peer connected to it, and
between routers connected to each other; the robots' services and the fleet's clients connect to
it (deploy/site/). It runs until SIGTERM / SIGINT, tells systemd READY=1 once it listens, and logs
the sessions it routes for every minute.
"""

from __future__ import annotations

import logging
import signal
import threading

import zenoh

from h3edge.io.zenoh_session import open_session
from h3edge.serving.systemd import Notifier

log = logging.getLogger(__name__)


def run_router(zconf: zenoh.Config, stop: threading.Event | None = None, notifier: Notifier | None = None) -> int:
    """Route until SIGTERM / SIGINT / ``stop`` with ``zconf`` (its mode set to router here). The exit code."""
    stop = stop or threading.Event()
    notifier = notifier or Notifier()
    zconf.insert_json5("mode", '"router"')
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda signum, _frame: stop.set())
    with open_session(zconf) as session:
        info = session.info
        log.info("h3edge router %s listening on %s", info.zid(), zconf.get_json("listen/endpoints"))
        notifier.ready("routing")
        while not stop.wait(60.0):
            log.info("routing for %d peers / clients, %d routers", len(list(info.peers_zid())),
                     len(list(info.routers_zid())))
    log.info("h3edge router stopped")
    return 0
