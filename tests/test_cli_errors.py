"""Bad input as a user meets it: the `romannet` command as a real process, real files, real ports held by
a real socket. Each mistake must give one line on stderr naming the problem (and the file), exit 2, and
never a traceback."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from romannet.common.zenoh_session import free_port

ROOT = Path(__file__).resolve().parents[1]
# The installed entry point, as a user runs it (the module where the venv's script is not there).
_SCRIPT = shutil.which("romannet", path=str(Path(sys.executable).parent))
COMMAND = [_SCRIPT] if _SCRIPT else [sys.executable, "-m", "romannet.cli"]


def romannet(*args: str, timeout_s: float = 60) -> subprocess.CompletedProcess:
    env = dict(os.environ, ROMANNET_LOG_LEVEL="WARNING")
    env.pop("ROMANNET_ZENOH_CONFIG", None)
    return subprocess.run([*COMMAND, *args], capture_output=True, text=True, timeout=timeout_s, env=env, cwd=ROOT)


def one_line_error(out: subprocess.CompletedProcess, *needles: str) -> str:
    """The single stderr line of a refused command, after checking it says each needle."""
    assert out.returncode == 2, (out.returncode, out.stderr)
    assert "Traceback" not in out.stderr, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


# ---------------------------------------------------------------------------------------- config files
def test_config_that_is_a_directory(tmp_path: Path) -> None:
    one_line_error(romannet("info", "--config", str(tmp_path)), str(tmp_path), "is a directory")


def test_config_that_is_binary(tmp_path: Path) -> None:
    path = tmp_path / "weights.toml"
    path.write_bytes(bytes(range(256)) * 4)
    one_line_error(romannet("info", "--config", str(path)), str(path), "not valid TOML", "not UTF-8")


def test_config_with_a_bad_byte_inside_a_string(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_bytes(b'[reward]\nname = "\xff"\n')
    one_line_error(romannet("info", "--config", str(path)), str(path), "offset 17")


# ---------------------------------------------------------------------------------------- directories
def test_a_file_where_a_directory_belongs(tmp_path: Path) -> None:
    path = tmp_path / "notes.txt"
    path.write_text("a file, not a run")
    port = f"tcp/127.0.0.1:{free_port()}"
    for argv, named in ((["replay", "--dir", str(path), "--listen", port], path),
                        (["learner", "--run-dir", str(path), "--connect", port, "--max-updates", "1"], path),
                        (["actor", "--run-dir", str(path), "--actor-id", "a0", "--connect", port], path / "actors"),
                        (["up", "--runs-dir", str(path), "--name", "r", "--actors", "1"], path / "r")):
        one_line_error(romannet(*argv), str(named), "a file stands where a directory is needed")
    assert path.read_text() == "a file, not a run"


def test_a_replay_directory_whose_lock_cannot_be_opened(tmp_path: Path) -> None:
    (tmp_path / "replay" / "LOCK").mkdir(parents=True)
    one_line_error(romannet("replay", "--dir", str(tmp_path / "replay"), "--listen", f"tcp/127.0.0.1:{free_port()}"),
                   str(tmp_path / "replay" / "LOCK"), "Is a directory")


# ---------------------------------------------------------------------------------------- actor state
def _actor_dirs(tmp_path: Path) -> tuple[Path, Path]:
    state = tmp_path / "run" / "actors" / "actor-0" / "state.json"
    state.parent.mkdir(parents=True)
    episodes = tmp_path / "run" / "episodes" / "actor-0"
    episodes.mkdir(parents=True)
    return state, episodes


def test_damaged_actor_state_is_one_line_with_a_suggestion(tmp_path: Path) -> None:
    state, episodes = _actor_dirs(tmp_path)
    state.write_text('{"next_epi')  # cut off: a disk that lied
    for index in (3, 11):
        (episodes / f"ep{index:06d}.mcap").write_bytes(b"")
    line = one_line_error(romannet("actor", "--run-dir", str(tmp_path / "run"), "--actor-id", "actor-0"),
                          str(state), "not valid JSON", '{"next_episode": 12}')
    assert line.startswith("romannet actor: error: ")
    assert state.read_text() == '{"next_epi'  # left as it was for the user to look at


def test_actor_state_with_a_wrong_value(tmp_path: Path) -> None:
    state, _ = _actor_dirs(tmp_path)
    state.write_text(json.dumps({"next_episode": "seven"}))
    one_line_error(romannet("actor", "--run-dir", str(tmp_path / "run"), "--actor-id", "actor-0"),
                   str(state), '"next_episode" must be a whole number')


def test_resume_with_a_damaged_actor_state_is_refused_before_any_child_starts(tmp_path: Path) -> None:
    from romannet.common.config import load_config
    from romannet.common.configbase import write_toml

    run = tmp_path / "runs" / "r"
    write_toml(load_config(None, ['run_id="r"']), run / "config.toml")
    (run / "actors" / "actor-0").mkdir(parents=True)
    (run / "actors" / "actor-0" / "state.json").write_text('{"next_episode": 4}')
    damaged = run / "actors" / "actor-1" / "state.json"
    damaged.parent.mkdir(parents=True)
    damaged.write_bytes(b"\x00" * 64)  # zeroed by a disk that lied
    one_line_error(romannet("up", "--runs-dir", str(tmp_path / "runs"), "--name", "r", "--resume", "--actors", "2"),
                   str(damaged), "not valid JSON")
    assert not (run / "pids.json").exists() and not (run / "logs").exists()  # nothing was started


# ---------------------------------------------------------------------------------------- ports in use
@pytest.fixture
def held_port() -> Iterator[int]:
    """A loopback TCP port that a real socket is listening on for the whole test."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


def test_replay_listen_on_a_port_in_use(tmp_path: Path, held_port: int) -> None:
    endpoint = f"tcp/127.0.0.1:{held_port}"
    line = one_line_error(romannet("replay", "--dir", str(tmp_path / "replay"), "--listen", endpoint),
                          f"cannot listen on {endpoint}", "already in use")
    assert line.startswith("romannet replay: error: ")


def test_router_listen_on_a_port_in_use(held_port: int) -> None:
    one_line_error(romannet("router", "--listen", f"tcp/127.0.0.1:{held_port}"), "already in use")


def test_mcap_play_foxglove_on_a_port_in_use(tmp_path: Path, held_port: int) -> None:
    from _episodes import record_episode

    episode = tmp_path / "ep000000.mcap"
    record_episode(episode, 2)
    one_line_error(romannet("mcap", "play", str(episode), "--foxglove", str(held_port)),
                   f"cannot serve Foxglove on 127.0.0.1:{held_port}", "already in use")


def test_zenoh_open_errors_read_as_one_line() -> None:
    from romannet.common.zenoh_session import describe_open_error

    rust = " at /root/.cargo/git/checkouts/zenoh/io/zenoh-links/src/unicast.rs:338."
    assert describe_open_error("Can not create a new TCP listener bound to tcp/10.9.9.9:7447: [10.9.9.9:7447: "
                               "Cannot assign requested address (os error 99)" + rust + "]" + rust) == \
        "cannot listen on tcp/10.9.9.9:7447: Cannot assign requested address"
    assert describe_open_error("Cannot create a new TLS listener on 127.0.0.1:7447. Missing TLS private key."
                               + rust + rust) == \
        "Zenoh could not start: Cannot create a new TLS listener on 127.0.0.1:7447. Missing TLS private key."


# ---------------------------------------------------------------------------------------- usage and help
def _usage_error(out: subprocess.CompletedProcess) -> tuple[str, str]:
    """(usage text, the error line) of an argparse refusal."""
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    *usage, error = out.stderr.strip().splitlines()
    return "\n".join(usage), error


def test_bad_flag_after_a_verb_shows_the_verbs_usage_and_the_flag_meant(tmp_path: Path) -> None:
    usage, error = _usage_error(romannet("replay", "--dir", str(tmp_path), "--lisen", "tcp/127.0.0.1:7447"))
    assert usage.startswith("usage: romannet replay ") and "--listen ENDPOINT" in usage
    assert error == "romannet replay: error: unrecognized arguments: --lisen tcp/127.0.0.1:7447; did you mean --listen?"


def test_bad_flag_of_a_sub_verb_shows_that_sub_verbs_usage(tmp_path: Path) -> None:
    usage, error = _usage_error(romannet("deploy", "certs", str(tmp_path), "--rooter-host", "h", "--dayz=3"))
    assert usage.startswith("usage: romannet deploy certs ")
    assert error.startswith("romannet deploy certs: error: unrecognized arguments: --rooter-host h --dayz=3")
    assert "--rooter-host: did you mean --router-host?" in error and "--dayz: did you mean --days?" in error


def test_unknown_argument_without_a_near_flag_gets_no_guess() -> None:
    usage, error = _usage_error(romannet("info", "--zzzzzz"))
    assert usage.startswith("usage: romannet info ")
    assert error == "romannet info: error: unrecognized arguments: --zzzzzz"


def test_bench_learner_refuses_a_negative_thread_count_in_one_line() -> None:
    one_line_error(romannet("bench", "learner", "--threads", "-1"), "threads must be >= 0")


def test_bench_system_runs_the_parts_asked_for_and_refuses_unknown_ones(monkeypatch) -> None:
    one_line_error(romannet("bench", "system", "--parts", "latency,bogus"), "unknown part(s) bogus",
                   "throughput, latency, recipe, precisions, time")
    from romannet.bench import system
    from romannet.common import policy

    monkeypatch.setattr(policy, "resolve_inference_precision", lambda p: "fp32")
    result = system.run_system_benchmark(parts=("precisions",))  # "auto" is fp32: nothing to compare, no fleet
    assert result["recipe_precisions"]["left_out"] == 'precision "auto" is fp32 on this machine'
    assert result["throughput"] == [] and result["weights_latency"] == [] and "actor_time" not in result


def test_bench_system_late_part_needs_a_finished_run(tmp_path) -> None:
    one_line_error(romannet("bench", "system", "--parts", "late"), "part 'late' resumes a finished",
                   "--late-from RUN_DIR")
    one_line_error(romannet("bench", "system", "--parts", "time,late", "--late-from", str(tmp_path)),
                   f"{tmp_path} is not one")


def test_bench_faults_help_describes_the_faults_benchmark() -> None:
    out = romannet("bench", "faults", "--help")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage: romannet bench faults")
    for words in ("network-namespace hosts", "SIGKILL", "lost and duplicated", "root", "sudo romannet bench faults"):
        assert words in " ".join(out.stdout.split()), words
    assert "--inserts" not in out.stdout  # only the options this benchmark reads


def test_every_benchmark_deploy_tool_and_diagnostic_has_a_description_and_an_example() -> None:
    # In-process (the parsers `romannet` builds): one process per sub-command would cost seconds each.
    from romannet.cli import build_parser
    from romannet.cli_parser import chosen_parser

    parser = build_parser()
    tools = [("bench", b) for b in ("inference", "replay", "sim", "learner", "system", "pick-geometry",
                                            "place-geometry", "faults")]
    tools += [("deploy", t) for t in ("certs", "configs", "check")]
    tools += [("analyse", w) for w in ("pick-offsets", "stack-actions", "repeated-failures", "training-counts",
                                       "angle-probe")]
    for verb, tool in tools:
        args = argparse.Namespace(verb=verb, what=tool, tool=tool)
        text = chosen_parser(parser, args).format_help()
        assert text.startswith(f"usage: romannet {verb} {tool}"), text
        description = text.split("\n\n")[1]
        assert len(description.split()) > 10, (tool, description)  # a paragraph, not the usage again
        assert f"example:\n  {'sudo ' if tool == 'faults' else ''}romannet {verb} {tool} " in text, text


def test_mistyped_verb_gets_the_verb_meant() -> None:
    out = romannet("replya", "--dir", "x")
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert out.stderr.strip().splitlines()[-1].endswith("; did you mean replay?"), out.stderr


def test_choice_hints() -> None:
    from romannet.cli_parser import with_choice_hint

    msg = "argument <tool>: invalid choice: 'cert' (choose from 'certs', 'configs', 'check')"
    assert with_choice_hint(msg) == msg + "; did you mean certs?"
    far = "argument <benchmark>: invalid choice: 'zzz' (choose from 'inference', 'faults')"
    assert with_choice_hint(far) == far
    assert with_choice_hint("the following arguments are required: --out") == \
        "the following arguments are required: --out"


def test_live_views_on_a_port_in_use(tmp_path: Path, held_port: int) -> None:
    """`mcap live`, `actor --foxglove` and `up --foxglove`: one line, before any actor or fleet starts and
    before up makes the run's directory."""
    (tmp_path / "episodes" / "actor-0").mkdir(parents=True)
    needles = (f"cannot serve Foxglove on 127.0.0.1:{held_port}", "already in use")
    one_line_error(romannet("mcap", "live", str(tmp_path / "episodes"), "--foxglove", str(held_port)), *needles)
    one_line_error(romannet("actor", "--run-dir", str(tmp_path / "run"), "--foxglove", str(held_port)), *needles)
    one_line_error(romannet("up", "--runs-dir", str(tmp_path / "runs"), "--name", "fox", "--actors", "1",
                            "--max-actions", "1", "--foxglove", str(held_port)), *needles)
    assert not (tmp_path / "runs" / "fox").exists()  # no run directory the same command, fixed, would refuse


def test_every_verb_and_sub_command_help_ends_with_an_example() -> None:
    """The README's promise: `romannet <verb> [<sub-command>] --help` ends with a copy-paste example."""
    from romannet.cli import build_parser

    def walk(parser: argparse.ArgumentParser, path: tuple[str, ...]):
        yield path, parser
        for action in parser._actions:  # argparse keeps sub-commands only here
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield from walk(sub, (*path, name))

    missing = []
    for path, parser in walk(build_parser(), ()):
        if not path:
            continue
        text = parser.format_help().rstrip()
        example = text.rsplit("example:\n", 1)[-1] if "example:\n" in text else ""
        if not example.lstrip().startswith(("romannet ", "sudo romannet ")):
            missing.append(" ".join(path))
    assert not missing, f"no example at the end of --help: {missing}"
