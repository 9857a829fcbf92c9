"""`romannet router`: a Zenoh router run by zenoh-python, for machines without zenohd.

    run_router(make_router_config("deploy/zenoh/router.json5"), stop_event)

The config files are the same ones zenohd reads (`zenohd -c deploy/zenoh/router.json5`): mode "router",
listen endpoints, TLS and access control. Every connection and disconnection is logged with the peer's
address and, over mutual TLS, its certificate's common name (its identity in the access-control policy),
so the router's log shows who is on the fleet network.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zenoh

from romannet.common.errors import RomannetError
from romannet.common.zenoh_limits import RX_LIMITS
from romannet.common.zenoh_session import open_zenoh

log = logging.getLogger(__name__)


def make_router_config(config_file: str | Path | None, listen: Sequence[str] | None = None) -> zenoh.Config:
    """The router's zenoh.Config: the file (None: an open router on tcp/0.0.0.0:7447 with multicast
    scouting off), mode forced to "router", listen endpoints replaced when given."""
    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            raise RomannetError(f"zenoh config file {path} does not exist")
        try:
            config = zenoh.Config.from_file(str(path))
        except Exception as exc:  # zenoh names the offending key and position
            raise RomannetError(f"zenoh config file {path} is invalid: {exc}") from None
        mode = json.loads(config.get_json("mode") or "null")
        if mode not in (None, "router"):
            raise RomannetError(f"{path} is a {mode!r} config; `romannet router` needs mode \"router\"")
    else:
        config = zenoh.Config.from_json5('{listen: {endpoints: ["tcp/0.0.0.0:7447"]}, '
                                         'scouting: {multicast: {enabled: false}}, '
                                         f'transport: {{link: {{rx: {json.dumps(RX_LIMITS)}}}}}}}')
    config.insert_json5("mode", '"router"')
    if listen:
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    return config


def _describe(link: Any) -> str:
    who = f" as {link.auth_identifier!r}" if link.auth_identifier else ""
    via = f" on {','.join(link.interfaces)}" if link.interfaces else ""
    return f"{link.dst}{who}{via}"


def run_router(config: zenoh.Config, stop: threading.Event,
               ready: Callable[[zenoh.Session], None] | None = None) -> None:
    """Run the router until stop is set; ready(session) is called once it listens."""
    session = open_zenoh(config)  # a taken port, an unreadable certificate, ...: one ZenohOpenError line
    try:
        listeners = [
            session.info.declare_link_events_listener(
                lambda ev: log.info("%s %s: zid %s", "connected" if ev.kind == zenoh.SampleKind.PUT
                                    else "disconnected", _describe(ev.link), ev.link.zid)),
        ]
        endpoints = json.loads(config.get_json("listen/endpoints") or "[]")
        if isinstance(endpoints, dict):  # zenoh's mode-dependent form: {"router": [...], "peer": [...]}
            endpoints = endpoints.get("router", [])
        access = json.loads(config.get_json("access_control") or "{}")
        tls = json.loads(config.get_json("transport/link/tls") or "{}")
        log.info("router %s listening on %s (mutual TLS %s, access control %s)", session.zid(),
                 ", ".join(map(str, endpoints)) or "nothing",
                 "on" if tls.get("enable_mtls") else "off",
                 f"on, default {access.get('default_permission')}" if access.get("enabled") else "off")
        if not access.get("enabled"):
            log.warning("no access control: any client that reaches %s may publish and query anything; on a "
                        "shared network use the secure profile (romannet deploy certs, docs/deploy.md)",
                        ", ".join(map(str, endpoints)) or "this router")
        if ready is not None:
            ready(session)
        while not stop.wait(1.0):
            pass
        for listener in listeners:
            listener.undeclare()
    finally:
        started = time.monotonic()
        session.close()
        log.info("router stopped (closed in %.2f s)", time.monotonic() - started)
