"""Damaged episode files: real recordings (tests/_episodes.py, the actor's recorder) with real bytes damaged
(tests/_damage.py). A flipped byte costs the damaged chunk only, the reader names every damage in one line,
and `romannet mcap inspect` (run as a process) reports each file of a directory and goes on with the rest.
"""

from __future__ import annotations

import io
import json
import random
import subprocess
import sys
from pathlib import Path

import _damage as dmg
import pytest
from _episodes import record_episode
from mcap.writer import Writer

from romannet.cli import main
from romannet.common.episode_file import TRANSITION_TOPIC, EpisodeFileError, NotMcapError, read_episode

pytestmark = pytest.mark.timeout(180)  # CLI processes import torch: seconds each on a loaded box

STEPS = 8


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory):
    """A finished episode and an unfinished one (its writer died: no summary), STEPS steps each."""
    root = tmp_path_factory.mktemp("recorded")
    full = record_episode(root / "full.mcap", STEPS)
    unfinished = record_episode(root / "unfinished.mcap", STEPS, actor_id="a1", episode_id="ep000001", seed=3,
                                finish=False)
    return full, unfinished


def _read(path: Path) -> tuple[list[bytes], object]:
    ep = read_episode(path)
    return [m.data for m in ep.of(TRANSITION_TOPIC)], ep.health


def _in_order(got: list[bytes], original: list[bytes]) -> bool:
    """Every read transition is bit-equal to a recorded one, in recorded order, none twice."""
    positions = [original.index(g) for g in got if g in original]
    return len(positions) == len(got) and positions == sorted(set(positions))


# ------------------------------------------------------------------------------------------------ reader
@pytest.mark.parametrize("which", ["full", "unfinished"])
@pytest.mark.parametrize("chunk", [1, STEPS // 2, -1])
def test_a_flipped_byte_in_a_chunk_costs_that_chunk_only(recorded, tmp_path: Path, which: str, chunk: int) -> None:
    source = recorded[0] if which == "full" else recorded[1]
    data = source.path.read_bytes()
    got, health = _read(dmg.write(tmp_path / "bad.mcap", dmg.flip_in_chunk(data, chunk)))
    assert len(got) == STEPS - 1 and _in_order(got, source.transitions)
    assert health.state == "damaged" and len(health.damage) == 1
    start = dmg.chunks(data)[chunk].offset
    assert health.damage[0].startswith(f"chunk at bytes {start}-") and "CRC does not match" in health.damage[0]
    assert health.complete == (which == "full")
    if which == "full":  # the summary's statistics say how many there were
        assert health.expected[TRANSITION_TOPIC] == STEPS


def test_the_first_chunk_damaged_costs_its_step_when_the_summary_declares_the_channels(recorded,
                                                                                       tmp_path: Path) -> None:
    full, unfinished = recorded
    # The first chunk declares the channels. A finished file repeats them in its summary, so the messages of
    # the later chunks are read through it; an unfinished file has no summary: they are counted, not read.
    got, health = _read(dmg.write(tmp_path / "f.mcap", dmg.flip_in_chunk(full.path.read_bytes(), 0)))
    assert len(got) == STEPS - 1 and _in_order(got, full.transitions) and len(health.damage) == 1
    got, health = _read(dmg.write(tmp_path / "u.mcap", dmg.flip_in_chunk(unfinished.path.read_bytes(), 0)))
    assert got == [] and health.state == "damaged"
    assert "of channels declared only in a skipped chunk" in health.damage[-1]


@pytest.mark.parametrize("which", ["full", "unfinished"])
@pytest.mark.parametrize("at", [0, 1, 8])  # the opcode, the low and the high byte of the record length
def test_a_damaged_record_header_reads_on_at_the_next_whole_chunk(recorded, tmp_path: Path, which: str,
                                                                   at: int) -> None:
    source = recorded[0] if which == "full" else recorded[1]
    data = source.path.read_bytes()
    chunk = dmg.chunks(data)[STEPS // 2]
    got, health = _read(dmg.write(tmp_path / "bad.mcap", dmg.flipped(data, chunk.offset + at)))
    assert len(got) == STEPS - 1 and _in_order(got, source.transitions)
    assert health.state == "damaged" and f"no whole record starts at byte {chunk.offset}" in health.damage[0]


def test_a_damaged_summary_or_footer_costs_no_message(recorded, tmp_path: Path) -> None:
    full, _ = recorded
    data = full.path.read_bytes()
    got, health = _read(dmg.write(tmp_path / "s.mcap", dmg.zero_summary(data)))
    assert got == full.transitions and health.state == "damaged" and "summary" in health.damage[0]
    assert "CRC does not match" in health.damage[0]
    # A zeroed end reads as a file whose end is missing (a crash can leave zeros): truncated, all data read.
    got, health = _read(dmg.write(tmp_path / "z.mcap", dmg.zero_footer(data)))
    assert got == full.transitions and health.state == "truncated" and "after the data" in health.describe()
    # Both at once: a damaged summary and a broken record header, read on without the summary's index.
    got, health = _read(dmg.write(tmp_path / "b.mcap", dmg.flip_chunk_length(dmg.zero_summary(data), 3)))
    assert len(got) == STEPS - 1 and _in_order(got, full.transitions) and len(health.damage) == 2


def test_damaged_metadata_is_named_and_the_steps_are_read(recorded, tmp_path: Path) -> None:
    full, unfinished = recorded
    for which, name in ((0, "romannet"), (1, "config")):
        ep = read_episode(dmg.write(tmp_path / f"m{which}.mcap", dmg.flip_in_metadata(full.path.read_bytes(), which)))
        assert [m.data for m in ep.of(TRANSITION_TOPIC)] == full.transitions
        assert ep.health.damage == (f"the {name!r} metadata record at byte "
                                    f"{[r for r in dmg.records(full.path.read_bytes()) if r.opcode == 0x0C][which].offset}"
                                    " does not parse: skipped",)
        assert name not in ep.metadata
    # Without a summary the record is not named, and the episode is still read.
    ep = read_episode(dmg.write(tmp_path / "u.mcap", dmg.flip_in_metadata(unfinished.path.read_bytes())))
    assert [m.data for m in ep.of(TRANSITION_TOPIC)] == unfinished.transitions
    assert ep.health.damage[0].startswith("a metadata record at byte")


def test_the_data_section_crc_catches_a_changed_metadata_value_when_the_writer_kept_one(tmp_path: Path) -> None:
    buf = io.BytesIO()
    writer = Writer(buf, enable_data_crcs=True)
    writer.start()
    writer.add_metadata("romannet", {"run_id": "abc"})
    writer.finish()
    data = bytearray(buf.getvalue())
    data[[r for r in dmg.records(bytes(data)) if r.opcode == 0x0C][0].end - 1] ^= 0x01  # 'c' -> 'b': still parses
    ep = read_episode(dmg.write(tmp_path / "m.mcap", bytes(data)))
    assert ep.metadata["romannet"] == {"run_id": "abb"}
    assert ep.health.damage == ("the data section's CRC does not match: a byte outside the chunks changed (a "
                                "metadata record, a message index)",)


def test_random_single_byte_damage_never_costs_more_than_one_step(recorded, tmp_path: Path) -> None:
    full, _ = recorded
    data = full.path.read_bytes()
    rng = random.Random(31)
    lost = []
    for i in range(60):
        bad = bytearray(data)
        bad[rng.randrange(len(bad))] ^= 1 << rng.randrange(8)
        try:
            got, health = _read(dmg.write(tmp_path / f"r{i}.mcap", bytes(bad)))
        except EpisodeFileError as err:  # the Header's opcode: the file no longer reads as MCAP
            assert "not an MCAP file" in str(err)
            continue
        assert _in_order(got, full.transitions)
        lost.append(STEPS - len(got))
        # Every changed bit is seen (chunk, summary and data-section CRCs, record framing): --verify fails.
        assert health.state != "complete", (i, health)
    assert max(lost) <= 1 and len(lost) >= 55


def test_a_changed_metadata_value_in_an_actors_file_is_found(recorded, tmp_path: Path, capsys) -> None:
    """The actor's recorder keeps the data-section CRC: a flipped bit in a metadata value that still parses
    (a config number, an id) is damage, named in one line, and `inspect --verify` exits 1 on it."""
    full, _ = recorded
    data = full.path.read_bytes()
    for which in (0, 1):  # "romannet" (ids, seed), "config" (the resolved TOML)
        meta = [r for r in dmg.records(data) if r.opcode == 0x0C][which]
        bad = bytearray(data)
        bad[meta.end - 2] ^= 0x01  # inside the last value, still valid UTF-8: the record parses
        path = dmg.write(tmp_path / f"meta{which}.mcap", bytes(bad))
        got, health = _read(path)
        assert got == full.transitions  # nothing else is lost
        assert health.state == "damaged" and "the data section's CRC does not match" in health.damage[0]
        assert main(["mcap", "inspect", str(path), "--verify"]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"{path}: damaged: the data section's CRC" in err


def test_not_mcap_is_one_typed_error(tmp_path: Path) -> None:
    with pytest.raises(NotMcapError, match="x.mcap: not an MCAP file"):
        read_episode(dmg.write(tmp_path / "x.mcap", b"PK\x03\x04 a zip file, say"))


# ------------------------------------------------------------------------------------------------- inspect
def _romannet(*argv: str) -> subprocess.CompletedProcess[str]:
    exe = Path(sys.executable).with_name("romannet")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "romannet.cli"]
    return subprocess.run([*cmd, *argv], capture_output=True, text=True, timeout=60, check=False)


@pytest.fixture(scope="module")
def damaged_dir(recorded, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, int]]:
    """One directory with a good file and one of each damage; the steps each should still yield."""
    full, unfinished = recorded
    data, root = full.path.read_bytes(), tmp_path_factory.mktemp("damaged")
    files = {"good": (data, STEPS), "chunk": (dmg.flip_in_chunk(data, 2), STEPS - 1),
             "header": (dmg.flip_chunk_length(data, 3), STEPS - 1), "metadata": (dmg.flip_in_metadata(data), STEPS),
             "summary": (dmg.zero_summary(data), STEPS), "footer": (dmg.zero_footer(data), STEPS),
             "cut": (dmg.cut(data, 0.5), None), "unfinished": (unfinished.path.read_bytes(), STEPS),
             "text": (b"not a recording\n", None)}
    for name, (content, _) in files.items():
        dmg.write(root / f"{name}.mcap", content)
    return root, {name: steps for name, (_, steps) in files.items()}


def test_inspect_reports_every_file_of_a_damaged_directory_and_exits_1(damaged_dir) -> None:
    root, steps = damaged_dir
    done = _romannet("mcap", "inspect", str(root), "--json")
    assert done.returncode == 1 and "Traceback" not in done.stderr
    lines = done.stderr.splitlines()
    # One line per damaged or unreadable file, naming it; truncated and unfinished files are no error here.
    assert sorted(line.split(": ")[2] for line in lines) == sorted(
        str(root / f"{n}.mcap") for n in ("chunk", "header", "metadata", "summary", "text"))
    assert all(line.startswith("romannet mcap inspect: error: ") for line in lines)
    report = json.loads(done.stdout)
    by_name = {Path(e["path"]).stem: e for e in report["episodes"]}
    assert set(by_name) == set(steps) - {"text"} and len(report["errors"]) == 1
    for name, episode in by_name.items():
        if steps[name] is not None:
            assert episode["steps"] == steps[name], name
    assert {n: e["health"] for n, e in by_name.items()} == {
        "good": "complete", "chunk": "damaged", "header": "damaged", "metadata": "damaged", "summary": "damaged",
        "footer": "truncated", "cut": "truncated", "unfinished": "truncated"}
    assert by_name["chunk"]["steps_recorded"] == STEPS
    assert (report["totals"]["damaged"], report["totals"]["truncated"]) == (4, 3)


def test_inspect_text_names_the_damage_and_verify_fails_on_any(damaged_dir, capsys) -> None:
    root, _ = damaged_dir
    done = _romannet("mcap", "inspect", str(root / "chunk.mcap"), str(root / "cut.mcap"), str(root / "good.mcap"))
    assert done.returncode == 1 and done.stderr.count("\n") == 1
    assert "[DAMAGED: chunk at bytes" in done.stdout and f"{STEPS - 1} of {STEPS} steps read" in done.stdout
    assert "[TRUNCATED: read" in done.stdout and "[complete" in done.stdout
    done = _romannet("mcap", "inspect", str(root / "cut.mcap"), str(root / "good.mcap"), "--verify")
    assert done.returncode == 1 and done.stderr.startswith(f"romannet mcap inspect: error: {root / 'cut.mcap'}: ")
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    # Each file alone (in-process, the same entry point): --verify fails on anything less than intact.
    for name, plain, verify in (("good", 0, 0), ("cut", 0, 1), ("footer", 0, 1), ("unfinished", 0, 1),
                                ("chunk", 1, 1), ("summary", 1, 1), ("text", 1, 1)):
        assert main(["mcap", "inspect", str(root / f"{name}.mcap")]) == plain, name
        assert main(["mcap", "inspect", str(root / f"{name}.mcap"), "--verify"]) == verify, name
        _, err = capsys.readouterr()
        assert err.count("\n") == plain + verify and "Traceback" not in err, name
