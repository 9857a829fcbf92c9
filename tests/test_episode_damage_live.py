"""Damaged recordings fed to a real replay server by real processes: `romannet learner --offline DIR` (what
`romannet up --from-recordings DIR` runs) and `romannet mcap feed DIR` name each damaged or unreadable file
in one line, feed every intact chunk of the others and go on; the learner then trains, feed exits 1."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import _damage as dmg
import pytest
from _episodes import record_episode
from test_mcap_live import CONFIG, RUN

from romannet.common.episode_file import TRANSITION_TOPIC, read_episode
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.zenoh_session import free_port, make_config, open_session

pytestmark = pytest.mark.timeout(240)


def _romannet() -> list[str]:
    exe = Path(sys.executable).with_name("romannet")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "romannet.cli"]


@pytest.fixture(scope="module")
def damaged(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, set[bytes], dict[str, str]]:
    """A directory of one intact episode, three damaged ones and a text file; the transitions that can be
    read from it, and the problem each bad file should be reported with."""
    root = tmp_path_factory.mktemp("damaged-recordings")
    src = tmp_path_factory.mktemp("sources")
    eps = [record_episode(src / f"ep{i}.mcap", 5, actor_id=f"a{i}", episode_id=f"ep00000{i}", seed=i, run_id=RUN)
           for i in range(4)]
    damages = [lambda d: d, lambda d: dmg.flip_in_chunk(d, 2), lambda d: dmg.flip_chunk_length(d, 1),
               lambda d: dmg.flip_in_metadata(d, 0)]
    for i, (ep, damage) in enumerate(zip(eps, damages, strict=True)):
        dmg.write(root / f"a{i}" / f"ep00000{i}.mcap", damage(ep.path.read_bytes()))
    (root / "notes.mcap").write_text("not a recording\n")
    readable = {m.data for p in sorted(root.glob("a*/*.mcap")) for m in read_episode(p).of(TRANSITION_TOPIC)}
    assert len(readable) == 5 + 4 + 4 + 5
    problems = {str(root / "a1" / "ep000001.mcap"): "CRC does not match",
                str(root / "a2" / "ep000002.mcap"): "no whole record starts at byte",
                str(root / "a3" / "ep000003.mcap"): "'romannet' metadata record at byte",
                str(root / "notes.mcap"): "not an MCAP file"}
    return root, readable, problems


def _bad_lines(output: str, problems: dict[str, str]) -> dict[str, str]:
    """The output line naming each bad file, one per file."""
    found = {}
    for path in problems:
        lines = [line for line in output.splitlines() if f"{path}: " in line]
        assert len(lines) == 1, (path, lines)
        found[path] = lines[0]
    return found


def test_learner_offline_and_feed_report_damaged_files_and_go_on(damaged, tmp_path: Path) -> None:
    root, readable, problems = damaged
    (tmp_path / "run.toml").write_text(CONFIG)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    with open(tmp_path / "replay.log", "wb") as replay_log:
        replay = subprocess.Popen([*_romannet(), "replay", "--config", str(tmp_path / "run.toml"), "--dir",
                                   str(tmp_path / "replay"), "--listen", endpoint], stdout=replay_log,
                                  stderr=subprocess.STDOUT, env=env)
        try:
            learner = subprocess.run(
                [*_romannet(), "learner", "--config", str(tmp_path / "run.toml"), "--run-dir", str(tmp_path / "l"),
                 "--connect", endpoint, "--offline", str(root), "--max-updates", "1"],
                capture_output=True, text=True, timeout=180, env=env, check=False)
            out = learner.stdout + learner.stderr
            assert learner.returncode == 0, out
            assert "Traceback" not in out
            for path, line in _bad_lines(out, problems).items():
                assert problems[path] in line, line
            assert f"{len(readable)} transitions: {len(readable)} new" in out
            assert "3 damaged file(s) fed but for their damaged parts, 1 skipped (not an episode)" in out
            with open_session(make_config(listen=[], connect=[endpoint])) as session:
                assert ZenohReplayClient(session, RUN).stats()["size"] == len(readable)

            feed = subprocess.run([*_romannet(), "mcap", "feed", str(root), "--connect", endpoint, "--json",
                                   "--wait", "60"], capture_output=True, text=True, timeout=120, env=env, check=False)
            assert feed.returncode == 1 and "Traceback" not in feed.stderr, feed.stderr
            errors = [line for line in feed.stderr.splitlines() if line.startswith("romannet mcap feed: error: ")]
            assert len(errors) == len(problems)
            for path, line in _bad_lines("\n".join(errors), problems).items():
                assert problems[path] in line, line
            report = json.loads(feed.stdout.strip().splitlines()[-1])
            assert (report["files"], report["accepted"], report["duplicates"]) == (4, 0, len(readable))
            assert set(report["damaged_files"]) == set(problems) - {str(root / "notes.mcap")}
        finally:
            replay.terminate()
            replay.wait(30)
