"""Integration: the deploy configs on loopback, with a real `romannet router` process and real TLS.

A site (CA, certificates, configs) is generated per module with the router on 127.0.0.1:<free port>.
The secure profile's access-control policy is probed with real sessions of every identity (the same probe
`romannet bench faults` runs across network namespaces); a real `romannet replay` server refuses a
transition sent on another actor's insert key; `romannet deploy check` reports what is alive; the plain
profile's router and clients turn every put of the project's keys into BLOCK congestion control; a frozen
client is dropped within the 3 s lease and reconnects by itself.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from _wire_samples import transition

from romannet.bench.acl_probe import run_acl_probe
from romannet.common import wire
from romannet.common.keys import RunKeys
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.zenoh_session import NoReplyError, RemoteError, free_port, make_config, open_session
from romannet.deploy.pki import generate_site
from romannet.deploy.zenoh_configs import SiteLayout, write_site_configs

ACTORS = ("actor-0", "actor-1")
RUN = "secure-run"
SIDE_PX = 32


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "romannet.cli", *args]


class Proc:
    """A CLI subprocess with its output in a file; stopped (SIGINT, then SIGKILL) by the fixture."""

    def __init__(self, argv: list[str], log: Path):
        self.log = log
        self._fh = log.open("ab")
        self.proc = subprocess.Popen(argv, stdout=self._fh, stderr=subprocess.STDOUT)

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_for_output(self, text: str, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if text in self.output():
                return
            assert self.proc.poll() is None, f"exited with {self.proc.returncode}:\n{self.output()}"
            time.sleep(0.1)
        raise AssertionError(f"no {text!r} within {timeout_s} s:\n{self.output()}")

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._fh.close()
        return self.proc.returncode


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A secure site on 127.0.0.1:<free port> with its router running; yields the configs directory."""
    root = tmp_path_factory.mktemp("site")
    port = free_port()
    generate_site(root / "pki", ACTORS, ["127.0.0.1"])
    endpoint = f"tls/127.0.0.1:{port}"
    write_site_configs(root / "zenoh", SiteLayout(actor_ids=ACTORS, router_endpoints=(endpoint,),
                                                  listen=(endpoint,), pki_dir=str(root / "pki")))
    router = Proc(_cli("router", "--zenoh-config", str(root / "zenoh" / "router.json5")), root / "router.log")
    try:
        router.wait_for_output("listening on")
        yield root / "zenoh"
    finally:
        assert router.stop() == 0, router.output()
    assert "as 'operator'" in router.output()  # the log names each client by its certificate


def test_access_control_holds_for_every_role(site: Path) -> None:
    results = run_acl_probe(site, ACTORS)
    failed = [r for r in results if not r["ok"]]
    assert not failed, json.dumps(failed, indent=1)
    by_name = {r["check"]: r["observed"] for r in results}
    # The rules, each observed (not merely configured):
    assert by_name["actor-0 publishes weights announcements"] == "denied"
    assert by_name["actor-0 publishes exploration rates"] == "denied"
    assert by_name["actor-0 serves weights to actor-1"] == "denied"
    assert by_name["actor-0 inserts under actor-1's id"] == "denied"
    assert by_name["actor-0 reads actor-1's transitions (queryable on actor-1's insert key)"] == "denied"
    assert by_name["actor-0 answers sample queries"] == "denied"
    assert by_name["actor-0 queries the router admin space"] == "denied"
    assert by_name["operator queries the router admin space"] == "allowed"
    assert by_name["a client without a certificate connects"] == "refused"
    assert by_name["a client with a certificate from another CA connects"] == "refused"
    assert sum(r["expected"] == "allowed" for r in results) >= 8  # each denial has a working path beside it


def _session(site: Path, identity: str):
    return open_session(make_config(site / f"{identity}.json5"))


def test_replay_server_takes_each_actors_transitions_on_its_own_key_only(site: Path, tmp_path: Path) -> None:
    config = tmp_path / "run.toml"
    # No learner samples here: unpaced.
    config.write_text(f'run_id = "{RUN}"\n[workspace]\nresolution_m = 0.014\n[replay]\nmin_size_to_sample = 1\n'
                      "samples_per_insert = 0.0\n")
    replay = Proc(_cli("replay", "--config", str(config), "--dir", str(tmp_path / "replay"), "--zenoh-config",
                       str(site / "replay.json5")), tmp_path / "replay.log")
    try:
        replay.wait_for_output("replay server ready")
        with _session(site, "actor-0") as session:
            own = ZenohReplayClient(session, RUN, actor_id="actor-0")
            ack = own.insert(transition(SIDE_PX, SIDE_PX, actor_id="actor-0", episode_id="ep000000", step=0),
                             timeout_s=20)
            assert ack.status == "accepted"
            # The router lets actor-0 use its own key; the server checks the payload names the same actor.
            forged = wire.encode_transition(transition(SIDE_PX, SIDE_PX, actor_id="actor-1", step=0))
            with pytest.raises(RemoteError) as err:
                own.insert_encoded(forged, timeout_s=10)
            assert err.value.reason == "wrong_actor", err.value
            # actor-1's key is not actor-0's to use: the router drops the query, nothing answers.
            other = ZenohReplayClient(session, RUN, actor_id="actor-1")
            with pytest.raises(NoReplyError):
                other.insert_encoded(forged, timeout_s=2)
        check = subprocess.run(_cli("deploy", "check", "--zenoh-config", str(site / "operator.json5"), "--run-id",
                                    RUN, "--json", "--expect-actors", "1", "--timeout", "3"),
                               capture_output=True, text=True, timeout=60)
        report = json.loads(check.stdout)
        assert check.returncode == 1, check.stderr
        assert report["routers"] and report["replay_alive"] and report["replay"]["size"] == 1, report
        assert not report["learner_alive"] and report["actors_alive"] == [], report
        assert sorted(report["problems"]) == ["0 actor(s) alive, expected 1", "learner not alive"]
        keys = RunKeys(RUN)
        with _session(site, "learner") as learner, _session(site, "actor-1") as actor:
            tokens = [learner.liveliness().declare_token(keys.learner_alive),
                      actor.liveliness().declare_token(keys.actor_alive("actor-1"))]
            time.sleep(0.5)
            check = subprocess.run(_cli("deploy", "check", "--zenoh-config", str(site / "operator.json5"),
                                        "--run-id", RUN, "--expect-actors", "1", "--timeout", "3"),
                                   capture_output=True, text=True, timeout=60)
            for token in tokens:
                token.undeclare()
        assert check.returncode == 0, check.stdout + check.stderr
        assert "actors alive (1): actor-1" in check.stdout and check.stdout.rstrip().endswith("OK")
    finally:
        assert replay.stop() == 0, replay.output()
    assert "wrong_actor" in replay.output()


def test_plain_profile_makes_every_put_block(tmp_path: Path) -> None:
    """The router's qos.network rewrites forwarded puts of the project's keys to BLOCK, and each client's
    qos.publication makes its own puts BLOCK; other keys keep the default DROP."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    write_site_configs(tmp_path, SiteLayout(router_endpoints=(endpoint,), listen=(endpoint,)))
    assert sorted(p.name for p in tmp_path.glob("*.json5")) == [
        "actor.json5", "learner.json5", "operator.json5", "replay.json5", "router.json5"]
    router = Proc(_cli("router", "--zenoh-config", str(tmp_path / "router.json5")), tmp_path / "router.log")
    try:
        router.wait_for_output("listening on")
        bare = zenoh.Config.from_file(str(tmp_path / "actor.json5"))
        bare.insert_json5("qos", "{}")  # no client-side override: only the router's remains
        key = f"{RunKeys(RUN).root}/exploration"
        with _session(tmp_path, "learner") as sub_side, _session(tmp_path, "actor") as client, \
                open_session(bare) as plain:
            got: list[tuple[str, zenoh.CongestionControl]] = []
            subs = [sub_side.declare_subscriber(k, lambda s: got.append((s.payload.to_bytes().decode(),
                                                                          s.congestion_control)))
                    for k in (key, "elsewhere/x")]
            deadline = time.monotonic() + 30
            while not got and time.monotonic() < deadline:  # until the subscriber is known
                plain.put(key, b"probe")
                time.sleep(0.1)
            got.clear()
            client.put(key, b"client")  # DROP asked; the client's config overrides
            plain.put(key, b"plain")  # DROP asked and not overridden here; the router overrides
            plain.put("elsewhere/x", b"other")  # not a project key: stays DROP
            deadline = time.monotonic() + 30
            while len(got) < 3 and time.monotonic() < deadline:
                time.sleep(0.05)
            for s in subs:
                s.undeclare()
        assert dict(got) == {"client": zenoh.CongestionControl.BLOCK, "plain": zenoh.CongestionControl.BLOCK,
                             "other": zenoh.CongestionControl.DROP}, got
    finally:
        assert router.stop() == 0, router.output()


@pytest.mark.parametrize("case", ["missing", "peer", "bad_key"])
def test_router_refuses_unusable_configs(tmp_path: Path, case: str) -> None:
    path = tmp_path / "router.json5"
    if case == "peer":
        path.write_text('{mode: "peer", scouting: {multicast: {enabled: false}}}')
    elif case == "bad_key":
        path.write_text('{mode: "router", access_control: {enabled: true, rulez: []}}')
    done = subprocess.run(_cli("router", "--zenoh-config", str(path)), capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    expected = {"missing": "does not exist", "peer": "needs mode \"router\"", "bad_key": "rulez"}[case]
    assert expected in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_a_hung_client_is_dropped_within_the_lease_and_comes_back(tmp_path: Path) -> None:
    """SIGSTOP freezes a client (no keep-alives): its liveliness token must vanish within the configs' 3 s
    lease (plus a margin); after SIGCONT it reconnects by itself and its token is back."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    write_site_configs(tmp_path, SiteLayout(router_endpoints=(endpoint,), listen=(endpoint,)))
    key = RunKeys(RUN).actor_alive("actor-0")
    router = Proc(_cli("router", "--zenoh-config", str(tmp_path / "router.json5")), tmp_path / "router.log")
    hung = None
    try:
        router.wait_for_output("listening on")
        code = ("import sys, time, zenoh\n"
                "s = zenoh.open(zenoh.Config.from_file(sys.argv[1]))\n"
                "t = s.liveliness().declare_token(sys.argv[2])\n"
                "print('token up', flush=True)\n"
                "time.sleep(120)\n")
        hung = Proc([sys.executable, "-c", code, str(tmp_path / "actor.json5"), key], tmp_path / "hung.log")
        hung.wait_for_output("token up")
        events: list[tuple[float, zenoh.SampleKind]] = []
        with _session(tmp_path, "operator") as watcher:
            sub = watcher.liveliness().declare_subscriber(
                key, lambda s: events.append((time.monotonic(), s.kind)), history=True)
            deadline = time.monotonic() + 30
            while not events and time.monotonic() < deadline:
                time.sleep(0.05)
            assert events and events[-1][1] == zenoh.SampleKind.PUT, events
            stopped = time.monotonic()
            hung.proc.send_signal(signal.SIGSTOP)
            try:
                deadline = time.monotonic() + 15
                while events[-1][1] != zenoh.SampleKind.DELETE and time.monotonic() < deadline:
                    time.sleep(0.05)
            finally:
                hung.proc.send_signal(signal.SIGCONT)
            gone_after_s = events[-1][0] - stopped
            assert events[-1][1] == zenoh.SampleKind.DELETE, events
            # lease 3 s, keep-alives every 0.75 s; under 9 s tells it from Zenoh's default 10 s lease on a loaded box
            assert 1.0 < gone_after_s < 9.0, gone_after_s
            deadline = time.monotonic() + 15
            while events[-1][1] != zenoh.SampleKind.PUT and time.monotonic() < deadline:
                time.sleep(0.05)
            sub.undeclare()
        assert events[-1][1] == zenoh.SampleKind.PUT, events  # reconnected, token declared again
    finally:
        if hung is not None:
            hung.proc.kill()
            hung.stop()
        assert router.stop() == 0, router.output()
