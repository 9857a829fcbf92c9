"""Paths built from data are checked first (issue 31, point 6): the shared safe-name check, `romannet mcap
rescore --out` on crafted episode files (a real `romannet` process on real MCAP files from the actor's
recorder)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from _episodes import record_episode

from romannet.common.episode_file import END_METADATA, EPISODE_METADATA, EpisodeReader, read_episode
from romannet.common.errors import RomannetError
from romannet.common.safe_names import UnsafeNameError, is_safe_name, safe_name
from romannet.mcaptools.rewrite import EpisodeWriter

pytestmark = pytest.mark.timeout(120)

# (file name, the episode metadata a crafted file carries, the bad value its error line must show)
CRAFTED = [
    ("run-up.mcap", {"run_id": "../../escaped-run"}, "'../../escaped-run'"),
    ("run-dotdot.mcap", {"run_id": ".."}, "'..'"),
    ("actor-slash.mcap", {"actor_id": "a0/../../../escaped-actor"}, "'a0/../../../escaped-actor'"),
    ("episode-up.mcap", {"episode_id": "../../../escaped-episode"}, "'../../../escaped-episode'"),
    ("run-newline.mcap", {"run_id": "x\ny"}, "'x\\ny'"),
]


def test_safe_name_accepts_ids_and_refuses_what_could_leave_a_directory() -> None:
    for good in ("actor-0", "ep000000.rs-0123abcd", "run_1", "a" * 128, "...x", ".hidden"):
        assert is_safe_name(good) and safe_name(good, "id") == good
    for bad in ("", ".", "..", "a/b", "../x", "/abs", "a\\b", "a b", "a\x00b", "é", "a" * 129, None, 7):
        assert not is_safe_name(bad)
        with pytest.raises(UnsafeNameError) as err:
            safe_name(bad, "metadata run_id")
        assert isinstance(err.value, RomannetError) and "\n" not in str(err.value)
        assert str(err.value).startswith(f"metadata run_id = {bad!r}"[:40])
    long = "/" * 10_000
    with pytest.raises(UnsafeNameError) as err:
        safe_name(long, "x")
    assert len(str(err.value)) < 300  # a hostile value cannot flood the log line


def _craft(source: Path, target: Path, episode: dict[str, str]) -> Path:
    """A copy of `source` whose episode metadata says `episode` instead (every message kept as is)."""
    reader = EpisodeReader(source)
    messages = list(reader.messages())
    metadata = {name: dict(values) for name, values in reader.metadata.items()}
    end = metadata.pop(END_METADATA, None)
    metadata[EPISODE_METADATA] = {**metadata[EPISODE_METADATA], **episode}
    with EpisodeWriter(target, metadata) as writer:
        for msg in messages:
            channel = reader.channel_by_topic(msg.topic)
            assert channel is not None
            writer.write(channel, msg)
        if end is not None:
            writer.add_metadata(END_METADATA, end)
    return target


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def test_rescore_out_never_writes_outside_out_for_crafted_ids(tmp_path: Path) -> None:
    inputs, out = tmp_path / "in", tmp_path / "work" / "deep" / "out"
    good = record_episode(inputs / "good.mcap", steps=3)
    absolute = str(tmp_path / "escaped-absolute")  # an absolute id would replace everything before it
    # Its shown value is cut to fit one line, where depends on the temporary path's length: not compared.
    crafted = [*CRAFTED, ("actor-absolute.mcap", {"actor_id": absolute}, "")]
    for name, episode, _ in crafted:
        _craft(good.path, inputs / name, episode)
    assert read_episode(inputs / "run-up.mcap").episode["run_id"] == "../../escaped-run"
    before = _files(tmp_path)
    cmd = [sys.executable, "-m", "romannet.cli", "mcap", "rescore", str(inputs), "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=100,
                          env={**os.environ, "ROMANNET_LOG_LEVEL": "WARNING"})
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    # Nothing new anywhere but under --out, and there only the good file's rescored episode.
    new = _files(tmp_path) - before
    assert all(out.resolve() in p.resolve().parents for p in new), sorted(map(str, new))
    assert [p.relative_to(out).parts[:2] for p in new] == [("mcap-test", "a0")]
    # One line per crafted file, naming the file and the bad value; the good file is reported as rescored.
    errors = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert len(errors) == len(crafted), proc.stderr
    for name, _, shown in crafted:
        mine = [line for line in errors if str(inputs / name) in line]
        assert len(mine) == 1 and shown in mine[0] and "cannot name a file or directory" in mine[0], errors
    assert f"{inputs / 'good.mcap'} -> {out}" in proc.stdout


def test_rescore_without_out_still_refuses_a_crafted_episode_id(tmp_path: Path, capsys) -> None:
    """The episode id also goes into every rescored transition (fed with --feed): it is checked always."""
    from romannet.mcaptools.rescore import RescoreSettings, rescore_file

    good = record_episode(tmp_path / "good.mcap", steps=2)
    crafted = _craft(good.path, tmp_path / "bad.mcap", {"episode_id": "../x"})
    assert rescore_file(good.path, RescoreSettings(), None).steps == 2
    with pytest.raises(RomannetError, match=r"bad\.mcap: metadata episode_id = '\.\./x' cannot name"):
        rescore_file(crafted, RescoreSettings(), None)
