"""Probe a secure site's router: does its access-control policy allow what each role needs and deny the rest?

    results = run_acl_probe(Path("site/zenoh"), actor_ids=("actor-0", "actor-1"))
    python -m romannet.bench.acl_probe --configs site/zenoh --actors actor-0,actor-1 --json

Opens one real Zenoh session per identity with that identity's config from `--configs` (the files
`romannet deploy certs` wrote): replay, learner, operator and two actors, A (the intruder) and B (the
victim). Everything happens under a run id of its own (`acl-probe-<random>`), so a fleet training on the
same router is not disturbed. Each denial is paired with the allowed action that proves the path works
(the learner's weights reach B, but A's do not; B's inserts reach the replay server, but A's under B's
id do not, ...), so a denial can never pass because nothing works at all. Clients without a certificate
and with a certificate from another CA must fail to connect.

Each check is {"check", "expected": "allowed" | "denied" | "connected" | "refused", "observed", "ok"}.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import zenoh

from romannet.common.keys import RunKeys

log = logging.getLogger(__name__)

SETTLE_S = 1.0  # after the allowed messages arrived: how long a forged one sent beside them gets to arrive
ARRIVAL_TIMEOUT_S = 15.0  # how long an allowed message may take (a loaded machine starting a fleet)
QUERY_TIMEOUT_S = 10.0  # a denied query ends at once (the router answers it finished); an allowed one on reply


class _Inbox:
    """Thread-safe record of what a callback received: (key, payload) pairs."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.items: list[tuple[str, bytes]] = []

    def add(self, key: str, payload: bytes) -> None:
        with self._lock:
            self.items.append((key, payload))

    def payloads(self) -> list[bytes]:
        with self._lock:
            return [p for _, p in self.items]

    def sample_cb(self) -> Callable[[zenoh.Sample], None]:
        return lambda s: self.add(str(s.key_expr), s.payload.to_bytes())

    def query_cb(self, answer: bytes) -> Callable[[zenoh.Query], None]:
        def on_query(q: zenoh.Query) -> None:
            self.add(str(q.key_expr), q.payload.to_bytes() if q.payload is not None else b"")
            q.reply(q.key_expr, answer)
        return on_query


def _config(path: Path) -> zenoh.Config:
    return zenoh.Config.from_file(str(path))


def _replies(session: zenoh.Session, key: str, payload: bytes | None = None,
             timeout_s: float = QUERY_TIMEOUT_S) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get(key, payload=payload, timeout=timeout_s)
            if r.ok is not None]


def _wait_until(fn: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if fn():
            return True
        time.sleep(0.05)
    return fn()


def _refused(config: zenoh.Config) -> str:
    """'refused' when the session cannot be opened, 'connected' when it could."""
    try:
        session = zenoh.open(config)
    except Exception as exc:  # zenoh raises ZError with "Unable to connect ..." here
        log.debug("refused as expected: %s", exc)
        return "refused"
    try:
        return "connected" if session.info.routers_zid() else "refused"
    finally:
        session.close()


def _fail_fast(config: zenoh.Config) -> zenoh.Config:
    config.insert_json5("connect/timeout_ms", "3000")
    config.insert_json5("connect/exit_on_failure", "true")
    return config


def _rogue_ca_config(actor_config: Path, work: Path, actor_id: str) -> zenoh.Config:
    """The actor's config with a certificate and key for the same CN, signed by a CA the site never made."""
    from romannet.deploy.pki import generate_site

    rogue = generate_site(work / "rogue", [actor_id], ["localhost"])
    config = _fail_fast(_config(actor_config))
    config.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(rogue[actor_id].cert)))
    config.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(rogue[actor_id].key)))
    return config


@contextmanager
def _sessions(configs: Path, names: Sequence[str]) -> Iterator[dict[str, zenoh.Session]]:
    with ExitStack() as stack:
        out = {}
        for name in names:
            session = zenoh.open(_config(configs / f"{name}.json5"))
            stack.callback(session.close)
            out[name] = session
        yield out


def run_acl_probe(configs: str | Path, actor_ids: Sequence[str] = ("actor-0", "actor-1")) -> list[dict[str, Any]]:
    """Run every check against the router the configs in `configs` point to; see the module docstring."""
    configs = Path(configs)
    if len(actor_ids) < 2:
        raise ValueError("the probe needs two actor identities (an intruder and a victim)")
    a, b = actor_ids[0], actor_ids[1]
    keys = RunKeys(f"acl-probe-{uuid.uuid4().hex[:8]}")
    results: list[dict[str, Any]] = []

    def check(name: str, expected: str, observed: str) -> None:
        results.append({"check": name, "expected": expected, "observed": observed, "ok": expected == observed})
        log.info("%-60s expected %-8s observed %s", name, expected, observed)

    def seen(flag: bool) -> str:
        return "allowed" if flag else "denied"

    with ExitStack() as stack:
        s = stack.enter_context(_sessions(configs, ["replay", "learner", "operator", a, b]))
        # A second operator session watches live episode topics (the first one replays an episode there).
        watcher = stack.enter_context(_sessions(configs, ["operator"]))["operator"]
        inserts, samples, priorities = _Inbox(), _Inbox(), _Inbox()
        fake_fetches, stolen, b_heard, sniffed = _Inbox(), _Inbox(), _Inbox(), _Inbox()
        live_seen, live_stolen = _Inbox(), _Inbox()
        declared: list[Any] = [
            # The real roles.
            s["replay"].declare_queryable(keys.replay_inserts, inserts.query_cb(b"replay-ack")),
            s["replay"].declare_queryable(keys.replay_sample, samples.query_cb(b"replay-batch")),
            s["replay"].declare_queryable(keys.replay_stats, _Inbox().query_cb(b"replay-stats")),
            s["replay"].declare_subscriber(keys.replay_priorities, priorities.sample_cb()),
            s["learner"].declare_queryable(keys.weights_fetch, _Inbox().query_cb(b"learner-weights")),
            s[b].declare_subscriber(keys.weights_announce, b_heard.sample_cb()),
            s[b].declare_subscriber(keys.weights_data, b_heard.sample_cb()),
            s[b].declare_subscriber(keys.exploration, b_heard.sample_cb()),
            # The intruder: serve what only the learner and the replay server may serve, listen to everything.
            s[a].declare_queryable(keys.weights_fetch, fake_fetches.query_cb(b"fake-weights")),
            s[a].declare_queryable(keys.replay_sample, fake_fetches.query_cb(b"fake-batch")),
            s[a].declare_queryable(keys.replay_insert(b), stolen.query_cb(b"stolen-ack")),
            s[a].declare_subscriber(f"{keys.root}/**", sniffed.sample_cb()),
            s[a].declare_subscriber(f"{keys.root}/actor/{b}/live/**", live_stolen.sample_cb()),
            watcher.declare_subscriber(keys.actors_live, live_seen.sample_cb()),
            s[a].liveliness().declare_token(keys.actor_alive(a)),
            s[a].liveliness().declare_token(keys.actor_alive(b)),  # impersonation
        ]
        stack.callback(lambda: [d.undeclare() for d in reversed(declared)])

        # The path works: B's own insert reaches the replay server (retried while declarations propagate).
        linked = _wait_until(lambda: b"replay-ack" in _replies(s[b], keys.replay_insert(b),
                                                                b"from-" + b.encode(), 1.0), ARRIVAL_TIMEOUT_S)
        check(f"{b} inserts under its own id", "allowed", seen(linked))
        check(f"{a} reads {b}'s transitions (queryable on {b}'s insert key)", "denied",
              seen(b"from-" + b.encode() in stolen.payloads()))

        own = _replies(s[a], keys.replay_insert(a), b"from-" + a.encode())
        check(f"{a} inserts under its own id", "allowed", seen(b"replay-ack" in own))
        other = _replies(s[a], keys.replay_insert(b), b"forged-by-" + a.encode())
        # (A's own queryable on B's key answers A locally; only the replay server's answer counts.)
        check(f"{a} inserts under {b}'s id", "denied",
              seen(b"replay-ack" in other or b"forged-by-" + a.encode() in inserts.payloads()))

        fed = _replies(s["learner"], keys.replay_insert(b), b"fed-by-learner")
        check(f"learner feeds recorded transitions of {b} (learner --offline)", "allowed",
              seen(b"replay-ack" in fed))

        s["learner"].put(keys.weights_announce, b"learner-announcement")
        s["learner"].put(keys.weights_data, b"learner-weights-put")
        s["learner"].put(keys.exploration, b"learner-rate")
        s["operator"].put(keys.actor_live(b, "/camera/color"), b"live-frame")
        s[a].put(keys.weights_announce, b"forged-announcement")
        s[a].put(keys.weights_data, b"forged-weights-put")
        s[a].put(keys.exploration, b"forged-rate")
        s[a].put(keys.replay_priorities, b"forged-priorities")
        s["learner"].put(keys.replay_priorities, b"learner-priorities")
        s["replay"].put(keys.weights_announce, b"replay-announcement")
        _wait_until(lambda: b"learner-rate" in b_heard.payloads() and b"learner-weights-put" in b_heard.payloads()
                    and b"learner-priorities" in priorities.payloads() and b"live-frame" in live_seen.payloads(),
                    ARRIVAL_TIMEOUT_S)
        time.sleep(SETTLE_S)  # the forged messages went out beside the learner's: as much time to arrive
        heard = b_heard.payloads()
        check("learner publishes weights announcements and rates", "allowed",
              seen(b"learner-announcement" in heard and b"learner-rate" in heard))
        check(f"{a} publishes weights announcements", "denied", seen(b"forged-announcement" in heard))
        check(f"learner puts weights to {b}", "allowed", seen(b"learner-weights-put" in heard))
        check(f"{a} puts weights", "denied", seen(b"forged-weights-put" in heard))
        check(f"{a} publishes exploration rates", "denied", seen(b"forged-rate" in heard))
        check("replay server publishes weights announcements", "denied", seen(b"replay-announcement" in heard))
        check("learner publishes priorities", "allowed", seen(b"learner-priorities" in priorities.payloads()))
        check(f"{a} publishes priorities", "denied", seen(b"forged-priorities" in priorities.payloads()))
        check(f"operator replays {b}'s episode live and watches it", "allowed",
              seen(b"live-frame" in live_seen.payloads()))
        check(f"{a} watches {b}'s live episode stream", "denied", seen(b"live-frame" in live_stolen.payloads()))
        others = [p for p in sniffed.payloads() if not p.startswith(b"forged")]  # A hears its own puts locally
        check(f"{a} subscribes to the run's traffic", "denied", seen(bool(others)))

        fetched = _replies(s[b], keys.weights_fetch)
        check(f"{b} fetches weights from the learner", "allowed", seen(b"learner-weights" in fetched))
        check(f"{a} serves weights to {b}", "denied", seen(b"fake-weights" in fetched or bool(fake_fetches.items)))
        batch = _replies(s["learner"], keys.replay_sample, b"request")
        check("learner samples from the replay server", "allowed", seen(b"replay-batch" in batch))
        check(f"{a} answers sample queries", "denied", seen(b"fake-batch" in batch))
        check(f"{a} samples from the replay server", "denied",
              seen(b"replay-batch" in _replies(s[a], keys.replay_sample)))

        check("operator queries replay stats", "allowed", seen(bool(_replies(s["operator"], keys.replay_stats))))
        check(f"{a} queries replay stats", "denied", seen(bool(_replies(s[a], keys.replay_stats))))
        check("operator queries the router admin space", "allowed",
              seen(bool(_replies(s["operator"], "@/*/router"))))
        check(f"{a} queries the router admin space", "denied", seen(bool(_replies(s[a], "@/*/router"))))
        check("learner queries the router admin space", "denied",
              seen(bool(_replies(s["learner"], "@/*/router"))))

        alive = {str(r.ok.key_expr) for r in s["operator"].liveliness().get(keys.actors_alive,
                                                                              timeout=QUERY_TIMEOUT_S)
                 if r.ok is not None}
        check(f"{a} declares its own liveliness", "allowed", seen(keys.actor_alive(a) in alive))
        check(f"{a} declares {b}'s liveliness", "denied", seen(keys.actor_alive(b) in alive))

    with tempfile.TemporaryDirectory(prefix="romannet-acl-") as tmp:
        # The control: with the same deadline, the site's own certificate gets in.
        check(f"a client with {a}'s certificate connects", "connected",
              _refused(_fail_fast(_config(configs / f"{a}.json5"))))
        no_cert = _fail_fast(_config(configs / f"{a}.json5"))
        no_cert.insert_json5("transport/link/tls/connect_certificate", "null")
        no_cert.insert_json5("transport/link/tls/connect_private_key", "null")
        check("a client without a certificate connects", "refused", _refused(no_cert))
        check("a client with a certificate from another CA connects", "refused",
              _refused(_rogue_ca_config(configs / f"{a}.json5", Path(tmp), a)))
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--configs", required=True, help="directory with router/replay/learner/operator/<actor>.json5")
    p.add_argument("--actors", default="actor-0,actor-1", help="two actor ids: intruder,victim")
    p.add_argument("--json", action="store_true", help="print the results as one JSON list")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.json else logging.INFO, format="%(message)s")
    results = run_acl_probe(args.configs, tuple(x for x in args.actors.split(",") if x))
    if args.json:
        sys.stdout.write(json.dumps(results) + "\n")
    return 0 if all(r["ok"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
