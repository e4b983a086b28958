"""The ``h3edge serve`` process: a :class:`MapService` behind zenoh, with signals and systemd.

Start-up: load (or resume) the map, run every kernel once on a throwaway map (compiled code is
loaded now, not at the first frame or query), open the zenoh session, declare keys, start the mapper
thread, then tell systemd READY=1. While running, WATCHDOG=1 goes out only while the mapper
thread's heartbeat is fresh (a wedged mapper stops the pings and systemd restarts the service).
SIGTERM / SIGINT: STOPPING=1, stop ingest, finish the frame in progress, write a final checkpoint,
close the session, exit 0.
"""

from __future__ import annotations

import logging
import signal
import threading
import time

from h3edge.config import Profile
from h3edge.io.zenoh_session import open_session
from h3edge.serving.server import ZenohServer
from h3edge.serving.service import MapService
from h3edge.serving.systemd import Notifier

log = logging.getLogger(__name__)


def serve(profile: Profile, zconf, resume: bool = False, stop: threading.Event | None = None,
          notifier: Notifier | None = None, ros: bool = False, resume_from_fleet: float | None = None) -> int:
    """Run the service until SIGTERM / SIGINT / ``stop``; ``ros``: also take the ROS 2 topics of the
    profile's ``[ros]`` table; ``resume_from_fleet``: seconds to wait for a fleet keeper's copy of
    the map when it is newer than the local checkpoint (after a lost disk), then resume. The exit code."""
    stop = stop or threading.Event()
    notifier = notifier or Notifier()
    cfg = profile.service
    if resume_from_fleet is not None:
        from pathlib import Path

        from h3edge.serving.keeping import restore_from_fleet

        with open_session(zconf) as session:  # closed again: the service opens its own below
            log.info("%s", restore_from_fleet(session, cfg.map_id, Path(cfg.state_dir) / cfg.map_id,
                                              resume_from_fleet))
        resume = True
    service = MapService(profile.map_settings(), cfg, profile.name, resume=resume, inference=profile.inference,
                         ros=profile.ros if ros else None)

    def on_signal(signum, _frame) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)
    log.info("warm-up (loading compiled kernels) took %.1f s", service.warm_up())
    session = open_session(zconf)
    server = ZenohServer(service, session, cfg.map_id, cfg.query_deadline_s)
    rc = 0
    try:
        server.start()
        service.start()
        notifier.ready(f"mapping {cfg.map_id}")
        log.info("h3edge serving map %r (profile %s, device %s, state %s)", cfg.map_id, profile.name,
                 service.mapper.device, service.checkpoints.path)
        ping = notifier.watchdog_interval()
        last_status = 0.0
        while not stop.wait(min(ping or 1.0, 1.0)):
            now = time.monotonic()
            if not service.alive:
                log.error("mapper thread died: exiting for a restart")
                rc = 1
                break
            if ping and now - service.heartbeat < 2 * ping:
                notifier.watchdog()
            if now - last_status > 10:
                s = service.status()
                notifier.status(f"{s['frames']['mapped']} frames mapped, {s['frames']['dropped']} dropped, "
                                f"{s['map']['voxels']} voxels")
                last_status = now
        notifier.stopping()
    finally:
        server.close()
        if not service.stop(checkpoint=True):  # the mapped frames since the last checkpoint are lost
            log.error("final checkpoint failed: %s", (service.last_error or {}).get("message"))
            rc = rc or 1
        elif cfg.fleet_checkpoints and server.checkpoint_publisher is not None:
            server.checkpoint_publisher.publish_new()  # the final one, for the fleet's keeper too
        session.close()
        log.info("h3edge stopped (exit %d)", rc)
    return rc
