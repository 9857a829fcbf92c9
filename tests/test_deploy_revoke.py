"""Revoking an actor's certificate the way docs/deploy.md says: `romannet deploy configs` without the actor
rewrites the router's access control, the router restarts with it, and the revoked certificate, still
valid under the site CA, connects but reaches nothing (its inserts and its liveliness token go nowhere,
the learner's announcements do not come to it) while a kept actor works on the same router. Real
`romannet` processes, real TLS, real Zenoh sessions."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
import zenoh

from romannet.common.keys import RunKeys
from romannet.common.zenoh_session import free_port
from romannet.deploy.pki import generate_site
from romannet.deploy.zenoh_configs import SiteLayout, write_site_configs

RUN = "revoke-run"
KEYS = RunKeys(RUN)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "romannet.cli", *args]


@pytest.fixture
def revoked_site(tmp_path: Path) -> Iterator[tuple[Path, Path]]:
    """(configs with actor-1 revoked, the configs issued before) with a router running on the first."""
    port = free_port()
    generate_site(tmp_path / "pki", ("actor-0", "actor-1"), ["127.0.0.1"])
    endpoint = f"tls/127.0.0.1:{port}"
    write_site_configs(tmp_path / "before", SiteLayout(actor_ids=("actor-0", "actor-1"), router_endpoints=(endpoint,),
                                                       listen=(endpoint,), pki_dir=str(tmp_path / "pki")))
    env = dict(os.environ, ROMANNET_LOG_LEVEL="WARNING")
    done = subprocess.run(_cli("deploy", "configs", str(tmp_path / "after"), "--actor-ids", "actor-0",
                               "--router-host", "127.0.0.1", "--port", str(port), "--pki-dir",
                               str(tmp_path / "pki")), capture_output=True, text=True, timeout=60, env=env)
    assert done.returncode == 0, done.stderr
    log = (tmp_path / "router.log").open("wb")
    router = subprocess.Popen(_cli("router", "--zenoh-config", str(tmp_path / "after" / "router.json5")),
                              stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while "listening on" not in (tmp_path / "router.log").read_text():
            assert router.poll() is None and time.monotonic() < deadline, (tmp_path / "router.log").read_text()
            time.sleep(0.1)
        yield tmp_path / "after", tmp_path / "before"
    finally:
        router.send_signal(signal.SIGINT)
        try:
            router.wait(30)
        except subprocess.TimeoutExpired:
            router.kill()
            router.wait()
        log.close()


def _open(path: Path) -> zenoh.Session:
    return zenoh.open(zenoh.Config.from_file(str(path)))


def _replies(session: zenoh.Session, key: str) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get(key, payload=b"t", timeout=5.0) if r.ok is not None]


@pytest.mark.timeout(120)
def test_a_revoked_actor_connects_but_reaches_nothing(revoked_site: tuple[Path, Path]) -> None:
    after, before = revoked_site
    assert "actor-1" not in (after / "router.json5").read_text()
    with ExitStack() as stack:
        sessions = {}
        for name, path in {"replay": after / "replay.json5", "operator": after / "operator.json5",
                           "learner": after / "learner.json5",
                           "actor-0": after / "actor-0.json5", "actor-1": before / "actor-1.json5"}.items():
            sessions[name] = _open(path)
            stack.callback(sessions[name].close)
        # The TLS handshake still succeeds: the certificate is signed by the site CA.
        assert sessions["actor-1"].info.routers_zid()
        asked: list[str] = []

        def on_insert(q: zenoh.Query) -> None:
            asked.append(str(q.key_expr))
            q.reply(q.key_expr, b"ack")

        queryable = sessions["replay"].declare_queryable(KEYS.replay_inserts, on_insert)
        stack.callback(queryable.undeclare)
        tokens = [sessions[a].liveliness().declare_token(KEYS.actor_alive(a)) for a in ("actor-0", "actor-1")]
        for token in tokens:
            stack.callback(token.undeclare)

        deadline = time.monotonic() + 20  # the kept actor's insert is the proof that the path works
        while not _replies(sessions["actor-0"], KEYS.replay_insert("actor-0")):
            assert time.monotonic() < deadline, "actor-0's insert never reached the replay server"
            time.sleep(0.2)
        assert _replies(sessions["actor-1"], KEYS.replay_insert("actor-1")) == []
        # Nothing of the fleet reaches it either: the learner's announcements arrive at actor-0 only.
        heard: dict[str, list[bytes]] = {"actor-0": [], "actor-1": []}
        for a in heard:
            sub = sessions[a].declare_subscriber(KEYS.weights_announce,
                                                 lambda s, a=a: heard[a].append(s.payload.to_bytes()))
            stack.callback(sub.undeclare)
        deadline = time.monotonic() + 20
        while not heard["actor-0"]:
            assert time.monotonic() < deadline, "actor-0 never heard the learner"
            sessions["learner"].put(KEYS.weights_announce, b"v1")
            time.sleep(0.2)
        sessions["learner"].put(KEYS.weights_announce, b"v2")
        while b"v2" not in heard["actor-0"]:
            assert time.monotonic() < deadline, "actor-0 never heard v2"
            time.sleep(0.05)
        time.sleep(0.5)  # v2 took one path to actor-0; the same to actor-1 would be here by now
        assert heard["actor-1"] == []
        alive = [str(r.ok.key_expr) for r in sessions["operator"].liveliness().get(KEYS.actors_alive, timeout=5.0)
                 if r.ok is not None]
        assert alive == [KEYS.actor_alive("actor-0")], alive
    assert asked and all(k == KEYS.replay_insert("actor-0") for k in asked), asked
