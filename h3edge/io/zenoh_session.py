"""Zenoh sessions: a config from a JSON5 file with command-line overrides, and opening a session
with a one-line error; shared by the service, the client, the publishers and the commands."""

from __future__ import annotations

import json

import zenoh


def zenoh_config(path: str | None = None, mode: str | None = None, connect: list[str] | None = None,
                 listen: list[str] | None = None, multicast: bool | None = None) -> zenoh.Config:
    """A zenoh config from a JSON5 file (or zenoh's defaults), with command-line overrides."""
    conf = zenoh.Config.from_file(path) if path else zenoh.Config()
    if mode:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if multicast is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    return conf


def open_session(conf: zenoh.Config) -> zenoh.Session:
    """Open a zenoh session; ConnectionError (one line) when zenoh cannot (e.g. client mode, no router)."""
    zenoh.init_log_from_env_or("error")
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise ConnectionError(f"cannot open a zenoh session: {str(e).split(' at /')[0]}") from None
