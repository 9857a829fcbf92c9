"""Opening Zenoh sessions and making one-reply queries, the way every component of the fleet does it.

Pitfalls this module exists to avoid (see docs and design section 2):
- A session that is never closed keeps Zenoh's threads alive and hangs the interpreter at exit, so
  sessions are only handed out by the `open_session` context manager, which closes in `finally`.
- Sessions do not survive `fork`: open them in the process that uses them (start children with spawn).
- Multicast scouting is off by default: on a shared machine it would join other people's sessions.
- `Session.get` without a timeout can wait forever, and with no matching queryable it returns at once
  with no reply. `query_one` turns both into a TimeoutError subclass, and an error reply into RemoteError.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import random
import re
import socket
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import zenoh

from .errors import RomannetError

log = logging.getLogger(__name__)

# The embedded default (same as deploy/zenoh-local.json5): peer mode on loopback, no multicast, and the
# fleet's message cap (common/zenoh_limits.py; each service lowers it to what its role receives).
DEFAULT_CONFIG_JSON5 = """{
  mode: "peer",
  listen: { endpoints: ["tcp/127.0.0.1:0"] },
  scouting: { multicast: { enabled: false }, gossip: { enabled: true } },
  transport: { link: { rx: { buffer_size: 65535, max_message_size: 268435456 } } },
}"""
# Pause between attempts while no queryable matches yet: right after a session opens, its connection
# and the remote declarations take ~0.1-0.5 s to arrive, and a get in that window returns no reply.
_RETRY_PAUSE_S = 0.05


class ZenohQueryError(RomannetError):
    """A Zenoh query did not produce a usable reply."""


class ZenohOpenError(RomannetError):
    """A Zenoh session could not be opened: a port in use, an address not on this machine, a certificate."""


class NoReplyError(ZenohQueryError, TimeoutError):
    """No queryable replied in time: the peer is not running, unreachable, or too slow."""


class RemoteError(ZenohQueryError):
    """The queryable replied with an error. `reason` is a short token (e.g. "rate_limited", "undecodable"),
    `detail` the human-readable rest of the message."""

    def __init__(self, key: str, reason: str, detail: str):
        self.key, self.reason, self.detail = key, reason, detail
        super().__init__(f"{key} refused the request ({reason}): {detail}")


# What Zenoh itself puts in the error reply that ends a query nobody answered in time (no queryable of ours
# sends it: theirs always carry a `<reason>: ` token). It means "no reply", not "refused".
_ZENOH_TIMEOUT_PAYLOAD = b"Timeout"


def format_error(reason: str, detail: str) -> bytes:
    """The payload of an error reply: `<reason>: <detail>` in UTF-8 (parsed by query_one)."""
    return f"{reason}: {detail}".encode()


def parse_error(payload: bytes) -> tuple[str, str]:
    """(reason, detail) of an error reply payload; reason is "error" when the payload has no token."""
    text = payload.decode("utf-8", errors="replace")
    reason, sep, detail = text.partition(": ")
    if not sep or not reason or " " in reason:
        return "error", text
    return reason, detail


_RUST_LOCATION = re.compile(r"\s*at /\S+\.rs:\d+\.?")  # where in Zenoh's Rust sources: no help to a user
_LISTEN_FAILURE = re.compile(r"listener bound to (?P<endpoint>\S+?):? \[\S+?: (?P<reason>[^\[\]]+?)"
                             r" \(os error (?P<errno>\d+)\)")


def describe_open_error(text: str) -> str:
    """One line for a user from the text of the ZError that zenoh.open raised."""
    m = _LISTEN_FAILURE.search(text)
    if m is not None:
        if int(m["errno"]) == errno.EADDRINUSE:
            return (f"cannot listen on {m['endpoint']}: the port is already in use (another process listens "
                    "there: stop it or choose another port)")
        return f"cannot listen on {m['endpoint']}: {m['reason']}"
    cleaned = " ".join(_RUST_LOCATION.sub("", text).split())
    return f"Zenoh could not start: {cleaned}"


def open_zenoh(config: zenoh.Config) -> zenoh.Session:
    """zenoh.open, with its failures (a port in use, a missing certificate) as one ZenohOpenError line."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise ZenohOpenError(describe_open_error(str(exc))) from None


# Ports handed out below the kernel's ephemeral range: a port from bind(0) lies inside it, where any outgoing
# connection or any session listening on port 0 may take it between the check and the listen.
_EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_LOWEST_PORT = 10000
_handed_out: set[int] = set()


def _ephemeral_low() -> int:
    try:
        return int(_EPHEMERAL_RANGE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _bindable(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago, drawn at random below the ephemeral range and never the same
    twice in one process. Still racy against another process listening there; fine for tests and for
    `romannet up` on one machine."""
    rng = random.SystemRandom()
    high = _ephemeral_low()
    if high - _LOWEST_PORT >= 1000:
        for _ in range(200):
            port = rng.randrange(_LOWEST_PORT, high)
            if port not in _handed_out and _bindable(host, port):
                _handed_out.add(port)
                return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:  # no room below the range: ask the kernel
        s.bind((host, 0))
        port = int(s.getsockname()[1])
    _handed_out.add(port)
    return port


def make_config(config_file: str | Path | None = None, listen: Sequence[str] | None = None,
                connect: Sequence[str] | None = None, multicast: bool = False) -> zenoh.Config:
    """A zenoh.Config from a json5 file (or the embedded loopback default), then overrides.

    listen / connect: endpoints like "tcp/127.0.0.1:7447"; None keeps the file's, [] clears them.
    multicast: multicast scouting; off unless asked, whatever the file says.
    """
    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            what = "is a directory" if path.is_dir() else "does not exist"
            raise ZenohOpenError(f"zenoh config file {path} {what}")
        config = zenoh.Config.from_file(str(path))
    else:
        config = zenoh.Config.from_json5(DEFAULT_CONFIG_JSON5)
    if listen is not None:
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect is not None:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    return config


@contextlib.contextmanager
def open_session(config: zenoh.Config | None = None) -> Iterator[zenoh.Session]:
    """Open a session (default: make_config()) and close it on exit, also on errors."""
    config = config if config is not None else make_config()
    if json.loads(config.get_json("mode") or "null") == "client":
        # A client config may wait for its router without end (connect.timeout_ms = -1): say so first.
        endpoints = json.loads(config.get_json("connect/endpoints") or "[]")
        if isinstance(endpoints, dict):  # zenoh's mode-dependent form
            endpoints = endpoints.get("client", [])
        log.info("connecting to the Zenoh router at %s", ", ".join(map(str, endpoints)) or "(no endpoint)")
    session = open_zenoh(config)
    try:
        yield session
    finally:
        session.close()


def query_one(session: zenoh.Session, key: str, payload: bytes | None = None, timeout_s: float = 10.0,
              parameters: str = "") -> bytes:
    """Send one query and return the payload of the first reply, as bytes.

    Raises NoReplyError (a TimeoutError) when nothing answered within timeout_s seconds, RemoteError when
    the queryable answered with an error. While no queryable matches (the get returns at once with no
    reply) the query is re-sent until the deadline: such a query was never delivered, so this is safe even
    for requests that are not idempotent.
    """
    deadline = time.monotonic() + timeout_s
    selector = f"{key}?{parameters}" if parameters else key
    attempts = 0
    while True:
        remaining_s = deadline - time.monotonic()
        if remaining_s <= 0:
            break
        attempts += 1
        started = time.monotonic()
        replies = session.get(selector, payload=payload, timeout=remaining_s,
                              congestion_control=zenoh.CongestionControl.BLOCK,
                              consolidation=zenoh.ConsolidationMode.NONE)
        for reply in replies:
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            payload = reply.err.payload.to_bytes()
            if payload == _ZENOH_TIMEOUT_PAYLOAD:
                continue  # Zenoh's own end of an unanswered query: NoReplyError below, never a refusal
            reason, detail = parse_error(payload)
            raise RemoteError(key, reason, detail)
        if time.monotonic() - started >= 0.9 * remaining_s:
            break  # it was delivered (or lost) and waited out the timeout: re-sending cannot help now
        time.sleep(min(_RETRY_PAUSE_S, max(0.0, deadline - time.monotonic())))
    raise NoReplyError(f"no reply from {key} within {timeout_s:.3g} s ({attempts} attempt(s)): is the "
                       "server running and reachable (check the listen/connect endpoints and the run id)?")


def wait_for_liveliness(session: zenoh.Session, key: str, timeout_s: float = 10.0) -> bool:
    """True once a liveliness token matching key is alive, False if none appeared within timeout_s."""
    deadline = time.monotonic() + timeout_s
    while True:
        remaining_s = deadline - time.monotonic()
        if remaining_s <= 0:
            return False
        for reply in session.liveliness().get(key, timeout=min(remaining_s, 1.0)):
            if reply.ok is not None:
                return True
        time.sleep(min(_RETRY_PAUSE_S, max(0.0, deadline - time.monotonic())))
