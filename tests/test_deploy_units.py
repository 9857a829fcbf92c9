"""The systemd unit templates in deploy/systemd/: systemd accepts them, they restart on failure, stop with
SIGINT, read an environment file, and their commands are ones `romannet` accepts (the learner's resumes
exactly when a checkpoint exists)."""

from __future__ import annotations

import configparser
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from romannet.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
UNITS = ROOT / "deploy" / "systemd"
INSTALLED = "/opt/romannet/venv/bin/romannet"
SERVICES = {"romannet-router.service": "router", "romannet-replay.service": "replay",
            "romannet-learner.service": "learner", "romannet-actor@.service": "actor"}


def _unit(name: str) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None, delimiters=("=",))
    parser.optionxform = str  # keys are case-sensitive in systemd
    parser.read_string((UNITS / name).read_text())
    return parser


def _environment(name: str, instance: str, extra: dict[str, str]) -> dict[str, str]:
    """Environment= lines of the unit (with %i), then its environment file's settings, as systemd does."""
    env: dict[str, str] = {}
    for line in (UNITS / name).read_text().splitlines():
        if line.startswith("Environment="):
            key, _, value = line[len("Environment="):].partition("=")
            env[key] = value.replace("%i", instance)
    env_file = UNITS / f"{SERVICES[name]}.env"
    for line in env_file.read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, _, value = line.partition("=")
            env[key.strip()] = value.strip()
    env.update(extra)
    return env


def _exec_argv(name: str, instance: str, env: dict[str, str], romannet: str) -> list[str]:
    """ExecStart after systemd's expansion: %i, ${VAR} from the environment, $$ -> $."""
    line = _unit(name)["Service"]["ExecStart"].replace("%i", instance)
    line = re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], line.replace("$$", "\0")).replace("\0", "$")
    return [romannet if part == INSTALLED else part.replace(INSTALLED, romannet) for part in shlex.split(line)]


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_units_restart_on_failure_and_stop_with_sigint(name: str) -> None:
    service = _unit(name)["Service"]
    assert service["Restart"] == "on-failure"
    assert service["KillSignal"] == "SIGINT"
    assert int(service["TimeoutStopSec"]) >= 20
    assert service["EnvironmentFile"] == f"-/etc/romannet/{SERVICES[name]}.env"
    assert (UNITS / f"{SERVICES[name]}.env").is_file()
    assert service["User"] == "romannet" and service["NoNewPrivileges"] == "yes"
    assert _unit(name)["Install"]["WantedBy"] == "multi-user.target"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
def test_systemd_accepts_the_units(tmp_path: Path) -> None:
    """`systemd-analyze verify` on copies that point at this checkout's romannet (it checks the binary)."""
    romannet = shutil.which("romannet", path=str(Path(sys.executable).parent))
    assert romannet, "romannet is not installed in this environment"
    for name in SERVICES:
        (tmp_path / name).write_text((UNITS / name).read_text().replace(INSTALLED, romannet))
    names = [n for n in SERVICES if "@" not in n] + ["romannet-actor@actor-0.service"]
    done = subprocess.run(["systemd-analyze", "verify", "--man=no", *names], cwd=tmp_path, capture_output=True,
                          text=True, timeout=60)
    problems = [line for line in done.stderr.splitlines() if "romannet" in line]
    assert done.returncode == 0 and not problems, done.stderr


@pytest.mark.parametrize("name", ["romannet-router.service", "romannet-replay.service", "romannet-actor@.service"])
def test_unit_commands_are_valid_romannet_commands(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    env = _environment(name, "actor-3", {})
    argv = _exec_argv(name, "actor-3", env, "romannet")
    assert argv[0] == "romannet"
    monkeypatch.setenv("ROMANNET_ZENOH_CONFIG", env["ROMANNET_ZENOH_CONFIG"])
    args = build_parser().parse_args(argv[1:])
    assert args.verb == SERVICES[name]
    assert args.zenoh_config == env["ROMANNET_ZENOH_CONFIG"]
    if args.verb == "actor":
        assert args.actor_id == "actor-3" and args.zenoh_config == "/etc/romannet/zenoh/actor-3.json5"
        assert args.config == "/etc/romannet/run.toml" and args.run_dir == "/var/lib/romannet/run"
    if args.verb == "replay":
        assert args.dir == "/var/lib/romannet/run/replay"


def test_learner_unit_resumes_exactly_when_a_checkpoint_exists(tmp_path: Path) -> None:
    """Runs the unit's shell command with a stand-in for romannet that prints its arguments."""
    stub = tmp_path / "romannet"
    stub.write_text('#!/bin/sh\nfor a in "$@"; do printf "%s\\n" "$a"; done\n')
    stub.chmod(0o755)
    run_dir = tmp_path / "run"
    env = _environment("romannet-learner.service", "", {"ROMANNET_RUN_DIR": str(run_dir)})
    argv = _exec_argv("romannet-learner.service", "", env, str(stub))
    assert argv[:2] == ["/bin/sh", "-c"]

    def started_with() -> list[str]:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=30, env={"PATH": os.environ["PATH"]})
        assert done.returncode == 0, done.stderr
        return done.stdout.splitlines()

    first = started_with()
    assert first == ["learner", "--config", "/etc/romannet/run.toml", "--run-dir", f"{run_dir}/learner"]
    args = build_parser().parse_args(first)
    assert not args.resume
    (run_dir / "learner" / "checkpoints").mkdir(parents=True)
    (run_dir / "learner" / "checkpoints" / "LATEST").write_text("ckpt-000100")
    again = started_with()
    assert again == [*first, "--resume"] and build_parser().parse_args(again).resume
