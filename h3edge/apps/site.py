"""The zenoh configs of a site (``h3edge deploy site``): one router with TLS and per-robot access
rules, and the configs its robots, keepers and clients connect with.

Every host has a certificate from the site's private CA whose common name is who it is: a robot's is
its map id. The router allows, by that name:

- a robot: to publish (frames, poses, live outputs, checkpoints), subscribe, declare queryables and
  reply only under its own ``h3edge/<map-id>/**``; to receive what is sent to its own keys and the
  fleet's wildcard status query;
- a keeper (``h3edge fleet keep``): to subscribe to and answer ``h3edge/*/checkpoint/**``;
- a client (planner, viewer): the read queries (status, profile, mesh, render, sdf, slice) of every
  map and the live outputs;
- an operator: also save, load and export.

Everything else is denied (``default_permission: "deny"``): a robot cannot answer, publish or keep
a checkpoint under another robot's id, and a certificate the site does not list can do nothing.
Zenoh matches a message's key by inclusion in a rule's key expression, so services answer on their
own key (``h3edge/<map-id>/status``), never the query's wildcard.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from h3edge.io.protocol import check_map_id

READ_KEYS = ["h3edge/*/status", "h3edge/*/profile", "h3edge/*/mesh", "h3edge/*/render", "h3edge/*/sdf",
             "h3edge/*/slice"]
OPERATE_KEYS = ["h3edge/*/save", "h3edge/*/load", "h3edge/*/export"]
CHECKPOINT_KEYS = ["h3edge/*/checkpoint/**"]


@dataclass
class Site:
    """Who is on a site, by certificate common name."""

    robots: list[str]
    """map ids of the robots' services (each robot's certificate CN)"""
    clients: list[str] = field(default_factory=list)
    """planners, viewers: read every map"""
    operators: list[str] = field(default_factory=list)
    """read every map, and save / load / export"""
    keepers: list[str] = field(default_factory=list)
    """hosts running h3edge fleet keep"""
    certs: str = "/etc/h3edge/tls"
    """folder holding ca.pem and <name>.pem / <name>-key.pem on each host"""
    router: str = "tls/site-router.local:7447"
    """the router's endpoint as the others connect to it"""
    listen: str = "tls/0.0.0.0:7447"
    """the router's listening endpoint"""

    def __post_init__(self) -> None:
        for r in self.robots:
            check_map_id(r)
        if not self.robots:
            raise ValueError("a site needs at least one robot")


def _tls(certs: str, name: str, listen: bool) -> dict:
    side = "listen" if listen else "connect"
    return {"root_ca_certificate": f"{certs}/ca.pem", f"{side}_private_key": f"{certs}/{name}-key.pem",
            f"{side}_certificate": f"{certs}/{name}.pem", "enable_mtls": True, "verify_name_on_connect": True}


def router_config(site: Site, name: str = "site-router") -> dict:
    """The router's zenoh config (a dict: write it as JSON, which JSON5 reads)."""
    rules, subjects, policies = [], [], []
    everyone = [*site.robots, *site.clients, *site.operators, *site.keepers]

    def rule(rid: str, flows: list[str], messages: list[str], keys: list[str]) -> None:
        rules.append({"id": rid, "permission": "allow", "flows": flows, "messages": messages, "key_exprs": keys})

    for r in site.robots:
        own = [f"h3edge/{r}/**"]
        rule(f"{r}-out", ["ingress"], ["put", "delete", "declare_subscriber", "declare_queryable", "query", "reply"],
             own)
        rule(f"{r}-in", ["egress"], ["put", "delete", "query", "reply"], own)
        subjects.append({"id": f"robot_{r}", "cert_common_names": [r]})
        policies.append({"rules": [f"{r}-out", f"{r}-in", "fleet-status", "declarations"], "subjects": [f"robot_{r}"]})
    rule("fleet-status", ["egress"], ["query"], ["h3edge/*/status"])
    rule("declarations", ["egress"], ["declare_subscriber", "declare_queryable"], ["h3edge/**"])
    rule("read", ["ingress"], ["query"], READ_KEYS)
    rule("read-replies", ["egress"], ["reply"], READ_KEYS)
    rule("live", ["ingress"], ["declare_subscriber"], ["h3edge/*/live/**"])
    rule("live-data", ["egress"], ["put"], ["h3edge/*/live/**"])
    rule("operate", ["ingress"], ["query"], OPERATE_KEYS)
    rule("operate-replies", ["egress"], ["reply"], OPERATE_KEYS)
    rule("keep", ["ingress"], ["declare_subscriber", "declare_queryable", "reply"], CHECKPOINT_KEYS)
    rule("keep-data", ["egress"], ["put", "query"], CHECKPOINT_KEYS)
    for sid, names, granted in (("clients", site.clients, ["read", "read-replies", "live", "live-data"]),
                                ("operators", site.operators, ["read", "read-replies", "live", "live-data",
                                                               "operate", "operate-replies"]),
                                ("keepers", site.keepers, ["keep", "keep-data"])):
        if names:
            subjects.append({"id": sid, "cert_common_names": list(names)})
            policies.append({"rules": [*granted, "declarations"], "subjects": [sid]})
    if len(set(everyone)) != len(everyone):
        raise ValueError("a name is listed twice: one certificate, one role")
    return {"mode": "router", "listen": {"endpoints": [site.listen]},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {"link": {"protocols": ["tls"], "tls": _tls(site.certs, name, listen=True),
                                   "rx": {"buffer_size": 16777216, "max_message_size": 67108864}}},
            "access_control": {"enabled": True, "default_permission": "deny", "rules": rules,
                               "subjects": subjects, "policies": policies}}


def host_config(site: Site, name: str) -> dict:
    """The zenoh config a robot's service, a keeper or a client named ``name`` connects with."""
    return {"mode": "client", "connect": {"endpoints": [site.router]}, "scouting": {"multicast": {"enabled": False}},
            "transport": {"link": {"protocols": ["tls"], "tls": _tls(site.certs, name, listen=False),
                                   "rx": {"buffer_size": 16777216, "max_message_size": 67108864}}}}


def write_site(site: Site, out: Path) -> list[Path]:
    """``router.json5`` and ``<name>.json5`` for every host of the site under ``out``; the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "router.json5"]
    written[0].write_text(json.dumps(router_config(site), indent=1) + "\n")
    for name in (*site.robots, *site.clients, *site.operators, *site.keepers):
        path = out / f"{name}.json5"
        path.write_text(json.dumps(host_config(site, name), indent=1) + "\n")
        written.append(path)
    return written
