"""`romannet router` and `romannet deploy certs|configs|check`: running the fleet across machines.

    romannet deploy certs site --actors 2 --router-host 10.0.0.2 --install-dir /etc/romannet
    romannet router --zenoh-config /etc/romannet/zenoh/router.json5
    romannet deploy check --zenoh-config /etc/romannet/zenoh/operator.json5 --run-id run-1 --expect-actors 2

See docs/deploy.md for the whole set-up. This module only parses arguments and prints; the work is in
pki.py, zenoh_configs.py and router.py beside it.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

log = logging.getLogger("romannet.deploy")

ENV_ZENOH_CONFIG = "ROMANNET_ZENOH_CONFIG"

ROUTER_EXAMPLE = ("romannet router --zenoh-config deploy/zenoh/router.json5\n"
                  "  romannet router --zenoh-config site/zenoh/router.json5   # after `romannet deploy certs site`")
CERTS_EXAMPLE = ("romannet deploy certs site --actors 2 --router-host 10.0.0.2 --install-dir /etc/romannet\n"
                 "  romannet deploy certs site --actors 3 --router-host 10.0.0.2 --install-dir /etc/romannet"
                 "   # add actor-2")
CONFIGS_EXAMPLE = ("romannet deploy configs site/zenoh --actors 2 --router-host 10.0.0.2   # plain TCP\n"
                   "  romannet deploy configs site/zenoh --actor-ids actor-0,actor-2 --router-host 10.0.0.2 "
                   "--pki-dir /etc/romannet/pki   # secure, actor-1 revoked")
CHECK_EXAMPLE = ("romannet deploy check --zenoh-config /etc/romannet/zenoh/operator.json5 --run-id run-1 "
                 "--expect-actors 2")
DEPLOY_EXAMPLE = "\n  ".join(e.split("\n")[0] for e in (CERTS_EXAMPLE, CONFIGS_EXAMPLE, CHECK_EXAMPLE))


def zenoh_config_default() -> str | None:
    """--zenoh-config's default for the service verbs: $ROMANNET_ZENOH_CONFIG if set and not empty."""
    return os.environ.get(ENV_ZENOH_CONFIG) or None


def add_zenoh_config_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--zenoh-config", metavar="FILE.json5", default=zenoh_config_default(),
                   help=f"Zenoh config file, e.g. deploy/zenoh/actor.json5 (default: ${ENV_ZENOH_CONFIG}, else "
                   "peer mode on loopback with multicast scouting off)")


# ------------------------------------------------------------------------------------------------ router
def add_router_arguments(p: argparse.ArgumentParser) -> None:
    add_zenoh_config_arg(p)
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="replace the config's listen endpoints, e.g. tls/0.0.0.0:7447 (repeatable)")


def cmd_router(args: argparse.Namespace) -> int:
    from romannet.common.signals import stop_on_signals
    from romannet.deploy.router import make_router_config, run_router

    config = make_router_config(args.zenoh_config, args.listen or None)
    stop = threading.Event()
    with stop_on_signals(stop, "closing the router"):
        run_router(config, stop)
    return 0


# ------------------------------------------------------------------------------------------------ deploy
def add_deploy_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="tool", required=True, metavar="<tool>")

    def site_args(q: argparse.ArgumentParser) -> None:
        q.add_argument("outdir", metavar="OUTDIR")
        q.add_argument("--actors", type=int, default=2, metavar="N", help="actor identities actor-0 .. actor-N-1")
        q.add_argument("--actor-ids", metavar="ID,ID,...", help="explicit actor ids instead of --actors")
        q.add_argument("--router-host", action="append", default=[], metavar="HOST",
                       help="name or address the clients dial for the router (repeatable; the first goes in "
                       "the client configs, all go in the router certificate); default: this host's name")
        q.add_argument("--port", type=int, default=7447, help="the router's port (default 7447)")

    def tool(name: str, help_text: str, description: str, example: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help_text, description=textwrap.fill(description, 100),
                              epilog=f"example:\n  {example}", formatter_class=argparse.RawDescriptionHelpFormatter)

    q = tool("certs", "a CA and certificates for router, replay, learner, operator and each actor (OUTDIR/pki), "
             "and the secure-profile Zenoh configs that use them (OUTDIR/zenoh)",
             "Writes a site for the secure profile: OUTDIR/pki/ holds a CA and a certificate and key for the "
             "router, replay, learner, operator and each actor (its common name is its identity in the "
             "router's access control), OUTDIR/zenoh/ one Zenoh config per role (mutual TLS; the router's "
             "denies by default and allows each identity its role's keys only). Run it again to add actors: "
             "the CA and existing certificates are kept. It prints which files go to which machine; keep "
             "pki/ca.key off the fleet (docs/deploy.md).", CERTS_EXAMPLE)
    site_args(q)
    q.add_argument("--install-dir", metavar="DIR", help="where OUTDIR will be on the machines (the paths in "
                   "the configs); default: OUTDIR itself")
    q.add_argument("--days", type=int, default=825, help="validity of the issued certificates")
    q.add_argument("--force", action="store_true", help="re-issue certificates that exist (the CA is kept)")

    q = tool("configs", "Zenoh configs only: the plain TCP profile, or with --pki-dir the secure one (regenerate "
             "the router's access control after adding or revoking an actor)",
             "Writes one Zenoh config per role (router, replay, learner, operator, each actor) into OUTDIR: "
             "the plain TCP profile for a network you trust, or with --pki-dir the secure one for "
             "certificates that `deploy certs` made. The router's access control lists exactly the actors "
             "named here, so this also rewrites it after adding an actor or revoking one (docs/deploy.md).",
             CONFIGS_EXAMPLE)
    site_args(q)
    q.add_argument("--pki-dir", metavar="DIR", help="secure profile: where the certificates are on the machines")

    q = tool("check", "connect with a config (the operator's) and report the router, the replay server, the "
             "learner and the actors of a run; exit 1 if something is missing",
             "Connects through the router with a Zenoh config (the operator's, in the secure profile) and "
             "reports what it finds of one run: the router, the replay server's liveliness and stats, the "
             "learner's liveliness and each live actor. Exit 0 when all are there (at least --expect-actors "
             "actors), 1 otherwise, naming what is missing.", CHECK_EXAMPLE)
    add_zenoh_config_arg(q)
    q.add_argument("--run-id", required=True, help="the run's id (its config's run_id)")
    q.add_argument("--expect-actors", type=int, default=1, metavar="N", help="fail with fewer live actors")
    q.add_argument("--timeout", type=float, default=5.0, help="seconds for each query")
    q.add_argument("--json", action="store_true", help="print one JSON object")


def _actor_ids(args: argparse.Namespace) -> tuple[str, ...]:
    if args.actor_ids:
        return tuple(a.strip() for a in args.actor_ids.split(",") if a.strip())
    if args.actors < 1:
        raise ValueError(f"--actors {args.actors} is invalid: a site needs at least one actor")
    return tuple(f"actor-{i}" for i in range(args.actors))


def _layout(args: argparse.Namespace, pki_dir: str | None):
    from romannet.deploy.zenoh_configs import SiteLayout

    hosts = args.router_host or [socket.gethostname()]
    scheme = "tls" if pki_dir is not None else "tcp"
    return SiteLayout(actor_ids=_actor_ids(args), router_endpoints=(f"{scheme}/{hosts[0]}:{args.port}",),
                      listen=(f"{scheme}/0.0.0.0:{args.port}",), pki_dir=pki_dir), hosts


def cmd_deploy(args: argparse.Namespace) -> int:
    if args.tool == "check":
        return _check(args)
    from romannet.deploy.zenoh_configs import write_site_configs

    outdir = Path(args.outdir)
    if args.tool == "configs":
        layout, _ = _layout(args, args.pki_dir)
        for path in write_site_configs(outdir, layout):
            log.info("wrote %s", path)
        return 0
    from romannet.deploy.pki import generate_site

    install = Path(args.install_dir) if args.install_dir else outdir.resolve()
    layout, hosts = _layout(args, str(install / "pki"))
    site = generate_site(outdir / "pki", layout.actor_ids, hosts, days=args.days, force=args.force)
    configs = write_site_configs(outdir / "zenoh", layout)
    lines = [f"site in {outdir} (paths in the configs point to {install}):",
             f"  every machine: {install}/pki/ca.pem",
             f"  router host ({', '.join(hosts)}): pki/router.pem pki/router.key zenoh/router.json5"]
    for name in site.identities:
        if name != "router":
            lines.append(f"  {name}: pki/{name}.pem pki/{name}.key zenoh/{name}.json5")
    lines.append(f"  keep pki/ca.key off the fleet's machines ({len(configs)} configs written)")
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def _check(args: argparse.Namespace) -> int:
    from romannet.common.keys import RunKeys, actor_id_from_alive_key
    from romannet.common.replay_client import ZenohReplayClient
    from romannet.common.zenoh_session import ZenohQueryError, make_config, open_session

    keys = RunKeys(args.run_id)
    report: dict[str, Any] = {"run_id": args.run_id, "config": args.zenoh_config}
    started = time.monotonic()
    with open_session(make_config(args.zenoh_config)) as session:
        report["routers"] = [str(z) for z in session.info.routers_zid()]

        def alive(key: str) -> list[str]:
            return sorted(str(r.ok.key_expr) for r in session.liveliness().get(key, timeout=args.timeout)
                          if r.ok is not None)

        report["replay_alive"] = bool(alive(keys.replay_alive))
        report["learner_alive"] = bool(alive(keys.learner_alive))
        report["actors_alive"] = [actor_id_from_alive_key(k) for k in alive(keys.actors_alive)]
        try:
            stats = ZenohReplayClient(session, args.run_id).stats(timeout_s=args.timeout)
            report["replay"] = {k: stats.get(k) for k in ("size", "inserts", "samples") if k in stats}
        except (ZenohQueryError, TimeoutError) as err:
            report["replay"] = {"error": str(err)}
    report["elapsed_s"] = round(time.monotonic() - started, 3)
    problems = []
    if not report["routers"]:
        problems.append("no router connected")
    if not report["replay_alive"]:
        problems.append("replay server not alive")
    if not report["learner_alive"]:
        problems.append("learner not alive")
    if len(report["actors_alive"]) < args.expect_actors:
        problems.append(f"{len(report['actors_alive'])} actor(s) alive, expected {args.expect_actors}")
    report["ok"], report["problems"] = not problems, problems
    if args.json:
        sys.stdout.write(json.dumps(report) + "\n")
    else:
        sys.stdout.write("\n".join([
            f"router(s): {', '.join(report['routers']) or 'NONE'}",
            f"replay server: {'alive' if report['replay_alive'] else 'NOT ALIVE'}  {report['replay']}",
            f"learner: {'alive' if report['learner_alive'] else 'NOT ALIVE'}",
            f"actors alive ({len(report['actors_alive'])}): {', '.join(report['actors_alive']) or '-'}",
            "OK" if not problems else "PROBLEMS: " + "; ".join(problems)]) + "\n")
    return 0 if not problems else 1
