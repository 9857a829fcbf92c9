"""Zenoh configs for a multi-machine site: one router, every role a client of it (plain TCP or mutual TLS).

    write_site_configs(Path("deploy/zenoh"), SiteLayout(actor_ids=("actor-0", "actor-1")))

The configs are plain Zenoh JSON5, read by zenoh-python (`--zenoh-config`) and by zenohd alike:

* Multicast scouting off (a robot lab's network is shared; nobody joins by accident) and gossip off:
  every client names the router it connects to.
* A short link lease (LEASE_MS): a hung or unplugged machine is noticed in a few seconds, its liveliness
  tokens vanish, and its client reconnects by itself once the network is back.
* A cap on message size (common/zenoh_limits.py): Zenoh holds a whole message before anyone can refuse
  it, so the bound on memory is in the config.
* BLOCK congestion control for every key of the project, enforced twice: each client's
  `qos.publication` makes its own puts BLOCK whatever the code asks, and the router's `qos.network`
  rewrites the puts and queries it forwards. (Queries and replies already default to BLOCK; the default
  DROP would lose large messages under load.)
* The secure profile adds TLS with mutual authentication: the router presents its certificate and asks
  each client for one signed by the site CA (romannet/deploy/pki.py); the client's certificate common name is its
  identity in the router's access-control policy, which denies by default (`access_control`, below).

Key expressions in the policy use `romannet/@v1/*/...`: any run id, this protocol version only.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from romannet.common.keys import PREFIX, check_chunk
from romannet.common.zenoh_limits import RX_LIMITS

LEASE_MS = 3000  # a silent link is declared dead after this; keep-alives every LEASE_MS / KEEP_ALIVE
KEEP_ALIVE = 4
ROUTER_PORT = 7447
ROLES = ("replay", "learner", "operator")  # the client roles besides the actors
_ANY_RUN = f"{PREFIX}/*"
# Reconnection attempts to the router: every 0.5 s at first, backing off to 4 s.
_RETRY = {"period_init_ms": 500, "period_max_ms": 4000, "period_increase_factor": 2}
_ADMIN_SPACE = "@/**"


@dataclass(frozen=True)
class SiteLayout:
    """What a site's configs depend on.

    router_endpoints: what clients dial (a name or address every machine can reach); listen: what the
    router binds. pki_dir: where the certificates will be on the machines (absolute in production);
    None writes the plain-TCP profile. actor_ids: one certificate and one access rule each.
    """

    actor_ids: tuple[str, ...] = ("actor-0", "actor-1")
    router_endpoints: tuple[str, ...] = (f"tcp/romannet-router:{ROUTER_PORT}",)
    listen: tuple[str, ...] = (f"tcp/0.0.0.0:{ROUTER_PORT}",)
    pki_dir: str | None = None
    lease_ms: int = LEASE_MS
    # How long a client tries to reach the router at start-up before giving up (-1: forever). A service
    # started by systemd before the router is up waits instead of crash-looping.
    connect_timeout_ms: int = -1

    def __post_init__(self) -> None:
        if not self.actor_ids:
            raise ValueError("a site needs at least one actor id")
        for actor_id in self.actor_ids:
            check_chunk("actor_id", actor_id)
            if actor_id in ("router", *ROLES):
                raise ValueError(f"actor id {actor_id!r} collides with a service identity")
        if len(set(self.actor_ids)) != len(self.actor_ids):
            raise ValueError(f"actor ids must be unique: {list(self.actor_ids)}")
        secure = self.pki_dir is not None
        for ep in (*self.router_endpoints, *self.listen):
            if secure != ep.startswith("tls/"):
                raise ValueError(f"endpoint {ep!r}: the {'secure' if secure else 'plain'} profile uses "
                                 f"{'tls/' if secure else 'tcp/'} endpoints")

    @property
    def secure(self) -> bool:
        return self.pki_dir is not None

    def pki(self, name: str) -> str:
        return f"{self.pki_dir}/{name}"


# ---------------------------------------------------------------------------------------- access rules
def _rule(rule_id: str, messages: Sequence[str], flow: str, keys: Sequence[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages),
            "key_exprs": [f"{_ANY_RUN}/{k}" if not k.startswith("@") else k for k in keys]}


def _role_rules(role: str) -> list[dict[str, Any]]:
    """The allow rules of one client role. ingress: what the client may send to the router; egress: what
    the router may deliver to it (a reply only reaches a client allowed to receive it, and so on)."""
    if role == "replay":
        served = ["replay/insert/*", "replay/sample", "replay/stats"]
        return [
            _rule("replay-serves", ["declare_queryable", "reply"], "ingress", served),
            _rule("replay-gets-requests", ["query"], "egress", served),
            _rule("replay-hears-priorities", ["declare_subscriber"], "ingress", ["replay/priorities"]),
            _rule("replay-gets-priorities", ["put"], "egress", ["replay/priorities"]),
            _rule("replay-is-alive", ["liveliness_token"], "ingress", ["replay/alive"]),
        ]
    if role == "learner":
        return [
            _rule("learner-samples", ["query"], "ingress", ["replay/sample", "replay/stats"]),
            _rule("learner-gets-batches", ["reply"], "egress", ["replay/sample", "replay/stats"]),
            _rule("learner-publishes", ["put"], "ingress",
                  ["replay/priorities", "weights/data", "weights/announce", "exploration"]),
            _rule("learner-serves-weights", ["declare_queryable", "reply"], "ingress", ["weights/fetch"]),
            _rule("learner-gets-fetches", ["query"], "egress", ["weights/fetch"]),
            _rule("learner-is-alive", ["liveliness_token"], "ingress", ["learner/alive"]),
            # `romannet learner --offline` feeds recorded episodes to the replay server under their actors'
            # ids: the learner is trusted with every insert key (the server still checks each payload's id).
            _rule("learner-feeds-recordings", ["query"], "ingress", ["replay/insert/*"]),
            _rule("learner-gets-feed-acks", ["reply"], "egress", ["replay/insert/*"]),
        ]
    if role == "operator":
        return [
            _rule("operator-controls", ["query"], "ingress", ["replay/stats", _ADMIN_SPACE]),
            _rule("operator-gets-answers", ["reply"], "egress", ["replay/stats", _ADMIN_SPACE]),
            _rule("operator-watches", ["declare_subscriber"], "ingress",
                  ["weights/announce", "exploration", "actor/*/live/**"]),
            _rule("operator-sees", ["put"], "egress", ["weights/announce", "exploration", "actor/*/live/**"]),
            # `romannet mcap play --zenoh`: recorded episodes replayed live on the actors' episode topics.
            _rule("operator-replays-episodes", ["put"], "ingress", ["actor/*/live/**"]),
            _rule("operator-watches-liveliness", ["declare_liveliness_subscriber", "liveliness_query"],
                  "ingress", ["**"]),
            _rule("operator-sees-liveliness", ["liveliness_token"], "egress", ["**"]),
        ]
    raise ValueError(f"unknown role {role!r}")


def _actor_rules(actor_id: str) -> list[dict[str, Any]]:
    own = f"replay/insert/{actor_id}"
    return [
        _rule(f"{actor_id}-inserts", ["query"], "ingress", [own]),
        _rule(f"{actor_id}-gets-acks", ["reply"], "egress", [own]),
        _rule(f"{actor_id}-is-alive", ["liveliness_token"], "ingress", [f"actor/{actor_id}/alive"]),
    ]


# What every actor may do besides its own inserts and liveliness: hear the learner.
_ACTORS_COMMON = [
    _rule("actors-listen", ["declare_subscriber"], "ingress", ["weights/data", "weights/announce", "exploration"]),
    _rule("actors-hear", ["put"], "egress", ["weights/data", "weights/announce", "exploration"]),
    _rule("actors-fetch-weights", ["query"], "ingress", ["weights/fetch"]),
    _rule("actors-get-weights", ["reply"], "egress", ["weights/fetch"]),
    _rule("actors-watch-learner", ["declare_liveliness_subscriber", "liveliness_query"], "ingress",
          ["learner/alive", "replay/alive"]),
    _rule("actors-see-learner", ["liveliness_token"], "egress", ["learner/alive", "replay/alive"]),
]


def access_control(actor_ids: Sequence[str]) -> dict[str, Any]:
    """The router's policy: deny by default; each identity (certificate CN) gets only its role's rules."""
    rules: list[dict[str, Any]] = [*_ACTORS_COMMON]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for role in ROLES:
        role_rules = _role_rules(role)
        rules += role_rules
        subjects.append({"id": role, "cert_common_names": [role]})
        policies.append({"id": f"{role}-policy", "subjects": [role], "rules": [r["id"] for r in role_rules]})
    for actor_id in actor_ids:
        own = _actor_rules(actor_id)
        rules += own
        subjects.append({"id": actor_id, "cert_common_names": [actor_id]})
        policies.append({"id": f"{actor_id}-policy", "subjects": [actor_id],
                         "rules": [r["id"] for r in (*_ACTORS_COMMON, *own)]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


# ---------------------------------------------------------------------------------------------- configs
def _common(layout: SiteLayout) -> dict[str, Any]:
    return {
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tx": {"lease": layout.lease_ms, "keep_alive": KEEP_ALIVE},
                               "rx": dict(RX_LIMITS)}},
    }


def _block_publication() -> dict[str, Any]:
    return {"publication": [{"key_exprs": [f"{PREFIX}/**"], "config": {"congestion_control": "block"}}]}


def router_config(layout: SiteLayout) -> dict[str, Any]:
    """The router: listens, forwards with BLOCK, and in the secure profile requires client certificates
    and enforces the access-control policy."""
    cfg: dict[str, Any] = {"mode": "router", "listen": {"endpoints": list(layout.listen)},
                           "connect": {"endpoints": []}, **_common(layout)}
    cfg["qos"] = {"network": [{"id": "romannet-block", "messages": ["put", "query"],
                               "key_exprs": [f"{PREFIX}/**"], "overwrite": {"congestion_control": "block"}}]}
    # Read-only admin space (`@/<router-zid>/router/**`): who is connected, what is declared. In the secure
    # profile only the operator identity may query it.
    cfg["adminspace"] = {"enabled": True, "permissions": {"read": True, "write": False}}
    if layout.secure:
        cfg["transport"]["link"]["tls"] = {
            "root_ca_certificate": layout.pki("ca.pem"), "enable_mtls": True,
            "listen_certificate": layout.pki("router.pem"), "listen_private_key": layout.pki("router.key"),
        }
        cfg["access_control"] = access_control(layout.actor_ids)
    return cfg


def client_config(layout: SiteLayout, identity: str) -> dict[str, Any]:
    """A client of the router; identity is a role ("replay", "learner", "operator"), an actor id, or in
    the plain profile (no identities) "actor" for any actor."""
    plain_actor = identity == "actor" and not layout.secure
    if identity not in ROLES and identity not in layout.actor_ids and not plain_actor:
        raise ValueError(f"unknown identity {identity!r}: one of {', '.join((*ROLES, *layout.actor_ids))}")
    cfg: dict[str, Any] = {
        "mode": "client",
        "connect": {"endpoints": list(layout.router_endpoints), "timeout_ms": layout.connect_timeout_ms,
                    "exit_on_failure": layout.connect_timeout_ms >= 0, "retry": dict(_RETRY)},
        "listen": {"endpoints": []}, **_common(layout), "qos": _block_publication(),
    }
    if layout.secure:
        cfg["transport"]["link"]["tls"] = {
            "root_ca_certificate": layout.pki("ca.pem"), "enable_mtls": True,
            "connect_certificate": layout.pki(f"{identity}.pem"),
            "connect_private_key": layout.pki(f"{identity}.key"),
            "verify_name_on_connect": True,
        }
    return cfg


# ------------------------------------------------------------------------------------------- JSON5 text
# Comments written above the top-level sections (why a value is what it is).
_CLIENT_COMMENTS = {
    "connect": "Wait for the router at start-up (timeout_ms -1) and reconnect after any outage, every 0.5-4 s.",
    "listen": "A client listens nowhere: every message goes through the router.",
}
_ROUTER_COMMENTS = {
    "listen": "Where every client dials in (the address in their configs must reach it).",
    "connect": "One router per site; list other routers here to join sites.",
}
_COMMENTS = {
    "scouting": "No multicast (a shared network must not join by accident), no gossip: the router is named.",
    "transport": (f"lease_ms {LEASE_MS}: a hung or unplugged machine is dropped, and its liveliness tokens vanish, "
                  "within a few seconds; rx: messages over 256 MiB are dropped on arrival (services lower it)."),
    "qos": "BLOCK congestion control for every key of the fleet (the default DROP loses large messages).",
    "adminspace": "Read-only admin space (@/<zid>/router/**): what is connected and declared.",
    "access_control": "Deny by default; each certificate common name gets its role's rules only.",
}
_INLINE_WIDTH = 100


def _format(value: Any, indent: int) -> str:
    """JSON text, with short lists and objects of plain values on one line (easier to read and diff)."""
    one_line = json.dumps(value)
    nested = isinstance(value, dict) and any(isinstance(v, (dict, list)) for v in value.values())
    if not isinstance(value, (dict, list)) or (len(one_line) + indent <= _INLINE_WIDTH and not nested):
        return one_line
    pad, inner = " " * indent, " " * (indent + 2)
    if isinstance(value, list):
        items = [inner + _format(v, indent + 2) for v in value]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    items = [f"{inner}{json.dumps(k)}: {_format(v, indent + 2)}" for k, v in value.items()]
    return "{\n" + ",\n".join(items) + "\n" + pad + "}"


def to_json5(cfg: Mapping[str, Any], header: Sequence[str]) -> str:
    """JSON5 text: a `//` header, a comment above each commented section, then JSON; zenoh and zenohd
    read it as is."""
    comments = {**_COMMENTS, **(_ROUTER_COMMENTS if cfg.get("mode") == "router" else _CLIENT_COMMENTS)}
    lines = [f"// {line}".rstrip() for line in header] + ["{"]
    items = list(cfg.items())
    for i, (key, value) in enumerate(items):
        if key in comments:
            lines.append(f"  // {comments[key]}")
        lines.append(f"  {json.dumps(key)}: {_format(value, 2)}{',' if i < len(items) - 1 else ''}")
    return "\n".join(lines) + "\n}\n"


def _header(layout: SiteLayout, what: str) -> list[str]:
    profile = "secure profile (mutual TLS + access control)" if layout.secure else "plain TCP profile"
    return [f"RoManNet fleet: {what}; {profile}.", "Generated by `romannet deploy` (romannet/deploy/zenoh_configs.py); "
            "see docs/deploy.md."]


def site_configs(layout: SiteLayout) -> dict[str, str]:
    """File name -> JSON5 text of every config of the site: router.json5 and one per client identity."""
    files = {"router.json5": to_json5(router_config(layout), _header(layout, "the Zenoh router"))}
    actors = layout.actor_ids if layout.secure else ("actor",)  # without certificates actors are alike
    for identity in (*ROLES, *actors):
        what = (f"client config of the {identity}" if identity in ROLES else "client config of any actor"
                if identity == "actor" else f"client config of actor {identity}")
        files[f"{identity}.json5"] = to_json5(client_config(layout, identity), _header(layout, what))
    return files


def write_site_configs(directory: Path, layout: SiteLayout) -> list[Path]:
    """Write site_configs(layout) into directory; returns the paths written."""
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in site_configs(layout).items():
        path = directory / name
        path.write_text(text, encoding="utf-8")
        written.append(path)
    return written
