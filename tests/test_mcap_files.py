"""Episode files without any server: the reader (complete, cut, not MCAP, foreign MCAP), `romannet mcap
inspect`, steps, `export`, `rescore` and the X/P/R re-scoring math. Files come from the real recorder
(tests/_episodes.py: scripted clutter steps on 32x32 heightmaps)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from _damage import chunks, flip_in_chunk, write
from _episodes import SIDE_PX, record_episode
from mcap.writer import Writer

from romannet.actor.recorder import count_steps
from romannet.cli import main
from romannet.common.config import RewardConfig, TaskConfig
from romannet.common.episode_file import (
    TRANSITION_TOPIC,
    EpisodeReader,
    ForeignMcapError,
    NotMcapError,
    episode_paths,
    read_episode,
)
from romannet.common.wire import decode_transition
from romannet.mcaptools.play import PlayOptions, delay_s
from romannet.mcaptools.rescore import rescored_id
from romannet.mcaptools.rescoring import SuccessRule, area_pixels, heightmap_success, rescore_step
from romannet.mcaptools.steps import group_steps, parse_transition

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def episodes(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("episodes")
    full = record_episode(root / "a0" / "ep000000.mcap", steps=6)
    crashed = record_episode(root / "a1" / "ep000001.mcap", steps=4, actor_id="a1", episode_id="ep000001", seed=3,
                             finish=False)
    return root, full, crashed


def _cut_in_the_middle(src: Path, dst: Path) -> int:
    """Copy src cut in the middle of a chunk; returns how many steps lie wholly before the cut."""
    data = src.read_bytes()
    cut = len(data) // 2
    dst.write_bytes(data[:cut])
    return count_steps(dst)


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# ------------------------------------------------------------------------------------------------ reader
def test_complete_file_reads_every_step_bit_equal(episodes) -> None:
    root, full, _ = episodes
    ep = read_episode(full.path)
    assert ep.health.complete and ep.health.problem == ""
    assert [m.data for m in ep.of(TRANSITION_TOPIC)] == full.transitions
    assert ep.episode["actor_id"] == "a0" and "run_id" in ep.config_toml
    assert ep.metadata["episode_end"]["done_reason"] == "step_limit"
    assert {c.schema_name for c in ep.channels} == {"foxglove.CompressedImage", "foxglove.RawImage",
                                                    "romannet.v1.Transition", "romannet.actor.Step"}
    assert episode_paths([root]) == [full.path, root / "a1" / "ep000001.mcap"]


def test_unfinished_and_cut_files_read_up_to_the_last_whole_chunk(episodes, tmp_path: Path) -> None:
    _, full, crashed = episodes
    ep = read_episode(crashed.path)  # the writer died after its last step: every step is there
    assert not ep.health.complete and "without a summary" in ep.health.problem
    assert [m.data for m in ep.of(TRANSITION_TOPIC)] == crashed.transitions
    whole = _cut_in_the_middle(full.path, tmp_path / "cut.mcap")
    assert 1 <= whole < len(full.transitions)
    cut = read_episode(tmp_path / "cut.mcap")
    assert not cut.health.complete and "ends inside a Chunk record" in cut.health.problem
    assert cut.health.read_bytes < cut.health.file_bytes
    assert [m.data for m in cut.of(TRANSITION_TOPIC)] == full.transitions[:whole]
    for n in (10, 200, 9 + len(full.path.read_bytes()) // 3):  # cut in the header, the metadata, a chunk
        (tmp_path / "c.mcap").write_bytes(full.path.read_bytes()[:n])
        assert [m.data for m in read_episode(tmp_path / "c.mcap").of(TRANSITION_TOPIC)] == \
            full.transitions[:count_steps(tmp_path / "c.mcap")]


def test_a_damaged_chunk_costs_that_chunk_only(episodes, tmp_path: Path) -> None:
    _, full, _ = episodes
    data = full.path.read_bytes()
    # A byte in the middle of the records of the last chunk but one (found by walking the records, see
    # tests/_damage.py): that chunk's CRC no longer matches, it is skipped and reading goes on after it.
    assert len(chunks(data)) >= 3
    ep = read_episode(write(tmp_path / "bad.mcap", flip_in_chunk(data, -2)))
    assert ep.health.state == "damaged" and "CRC does not match" in ep.health.damage[0]
    got = [m.data for m in ep.of(TRANSITION_TOPIC)]
    assert len(got) == len(full.transitions) - 1 and got == [t for t in full.transitions if t in got]


def _foreign_mcap(path: Path, with_metadata: bool) -> None:
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="someone else")
        if with_metadata:
            w.add_metadata("romannet", {"run_id": "x"})
        schema = w.register_schema("sensor_msgs/msg/Image", "ros2msg", b"uint32 height\nuint32 width\n")
        channel = w.register_channel("/camera/image_raw", "cdr", schema)
        w.add_message(channel, log_time=1, data=b"\x00" * 16, publish_time=1)
        w.finish()


def test_not_mcap_and_foreign_mcap_raise_one_typed_error_naming_the_file(tmp_path: Path) -> None:
    (tmp_path / "notes.mcap").write_text("hello, not a recording\n")
    (tmp_path / "empty.mcap").write_bytes(b"")
    for name in ("notes.mcap", "empty.mcap"):
        with pytest.raises(NotMcapError, match=f"{name}: not an MCAP file"):
            read_episode(tmp_path / name)
    (tmp_path / "magic.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(range(64)))  # the magic, then garbage
    with pytest.raises(NotMcapError, match="magic.mcap: not an MCAP file .the MCAP magic bytes are not followed"):
        read_episode(tmp_path / "magic.mcap")
    with pytest.raises(NotMcapError, match="no such file"):
        EpisodeReader(tmp_path / "missing.mcap")
    _foreign_mcap(tmp_path / "ros.mcap", with_metadata=False)
    with pytest.raises(ForeignMcapError, match="ros.mcap: no 'romannet' metadata"):
        read_episode(tmp_path / "ros.mcap")
    _foreign_mcap(tmp_path / "ros2.mcap", with_metadata=True)
    with pytest.raises(ForeignMcapError, match="ros2.mcap: channel '/camera/image_raw' has schema "
                       "'sensor_msgs/msg/Image'"):
        read_episode(tmp_path / "ros2.mcap")


def test_steps_pair_each_transition_with_its_observations_and_q_maps(episodes) -> None:
    _, full, _ = episodes
    steps = list(group_steps(EpisodeReader(full.path).messages()))
    assert len(steps) == len(full.transitions)
    for i, step in enumerate(steps):
        t = decode_transition(step.transition.data)
        assert step.record is not None and step.record["step"] == i
        assert set(step.q_maps) == {"push", "pick"}
        for obs, color in ((step.before, t.color_before), (step.after, t.color_after)):
            from romannet.mcaptools.render import decode_compressed

            img = cv2.cvtColor(decode_compressed(obs["/heightmap/color"].data), cv2.COLOR_BGR2RGB)
            np.testing.assert_array_equal(img, color)


# ------------------------------------------------------------------------------------------------ inspect
def test_inspect_reports_episodes_truncation_and_bad_files(episodes, tmp_path: Path, capsys) -> None:
    root, full, _ = episodes
    whole = _cut_in_the_middle(full.path, tmp_path / "cut.mcap")
    # A truncated or unfinished file (what a crashed writer leaves) is read up to its last whole chunk: exit 0,
    # except with --verify, which exits 1 for anything less than a complete, intact file, naming each.
    code, out, err = _run(capsys, "mcap", "inspect", str(root), str(tmp_path / "cut.mcap"), "--json", "--verify")
    assert code == 1 and err.count("\n") == 2 and "Traceback" not in err
    assert f"{root / 'a1' / 'ep000001.mcap'}: truncated" in err and f"{tmp_path / 'cut.mcap'}: truncated" in err
    assert json.loads(out)["totals"]["truncated"] == 2
    code, out, err = _run(capsys, "mcap", "inspect", str(root), str(tmp_path / "cut.mcap"), "--json")
    assert code == 0 and err == ""
    report = json.loads(out)
    a0, a1, cut = report["episodes"]
    assert (a0["steps"], a0["health"], a0["end_reason"]) == (6, "complete", "step_limit")
    assert a0["actions"] == {"push": 2, "pick": 4} and a0["successes"] == {"push": 2, "pick": 2}
    assert a0["reward_sum"] == pytest.approx(sum(full.rewards)) and a0["explored"] == 2
    assert a0["weights_versions"] == {"start": 0, "end": 2, "min": 0, "max": 2, "distinct": 3}
    assert a0["duration_s"] == pytest.approx(11.0) and a0["heightmap_px"] == [SIDE_PX, SIDE_PX]
    assert (a1["health"], a1["steps"], a1["end_reason"]) == ("truncated", 4, "step_limit")
    assert (cut["health"], cut["steps"], cut["end_reason"]) == ("truncated", whole, "unfinished")
    assert cut["read_bytes"] < cut["file_bytes"] and "last whole chunk" in cut["health_detail"]
    assert report["totals"]["steps"] == 10 + whole and report["errors"] == []

    code, out, _ = _run(capsys, "mcap", "inspect", str(full.path))
    assert code == 0 and "6 steps, successes push 2/2, pick 2/4" in out and "end: step_limit" in out

    (tmp_path / "junk.mcap").write_bytes(b"\x00" * 100)
    _foreign_mcap(tmp_path / "ros.mcap", with_metadata=False)
    for bad, problem in (("junk.mcap", "not an MCAP file"), ("ros.mcap", "no 'romannet' metadata")):
        code, out, err = _run(capsys, "mcap", "inspect", str(tmp_path / bad))
        assert code != 0 and out == ""
        assert err.count("\n") == 1 and "Traceback" not in err
        assert err.startswith(f"romannet mcap inspect: error: {tmp_path / bad}: {problem}")


# ------------------------------------------------------------------------------------------------- export
def test_export_writes_one_frame_per_step(episodes, tmp_path: Path, capsys) -> None:
    _, full, crashed = episodes
    code, out, err = _run(capsys, "mcap", "export", str(full.path), "--video", str(tmp_path / "ep.mp4"),
                          "--frames", str(tmp_path / "frames"), "--size", "128")
    assert code == 0, err
    frames = sorted((tmp_path / "frames").glob("step_*.png"))
    assert [p.name for p in frames] == [f"step_{i:05d}.png" for i in range(6)]
    first = cv2.imread(str(frames[0]))
    assert first.shape[0] % 2 == 0 and first.shape[1] % 2 == 0 and first.shape[0] > 128
    assert len({cv2.imread(str(p)).tobytes() for p in frames}) == 6  # every step looks different
    from romannet.mcaptools.video import video_codec

    assert video_codec(tmp_path / "ep.mp4") == ("h264", "yuv420p", 6)  # what browsers play; a frame a step
    data = (tmp_path / "ep.mp4").read_bytes()
    assert data.index(b"moov") < data.index(b"mdat")  # the index first: a browser plays it while loading
    code, _, err = _run(capsys, "mcap", "export", str(full.path), "--video", str(tmp_path), "--size", "64")
    assert code != 0 and err.strip().endswith("Is a directory") and "Traceback" not in err  # one line
    code, _, _ = _run(capsys, "mcap", "export", str(crashed.path), "--frames", str(tmp_path / "f2"))
    assert code == 0 and len(list((tmp_path / "f2").glob("*.png"))) == 4


# ------------------------------------------------------------------------------------------------ rescore
def test_rescore_with_the_recorded_config_reproduces_x_p_and_r(episodes, tmp_path: Path, capsys) -> None:
    root, full, _ = episodes
    code, out, err = _run(capsys, "mcap", "rescore", str(root), "--out", str(tmp_path / "same"), "--json")
    assert code == 0, err
    files = json.loads(out)["files"]
    assert [(f["steps"], f["success_changed"], f["reward_changed"]) for f in files] == [(6, 0, 0), (4, 0, 0)]
    new = read_episode(files[0]["output"])
    assert new.health.complete and new.episode["episode_id"] == files[0]["episode_id"]
    assert new.episode["episode_id"].startswith("ep000000.rs-") and new.metadata["rescore"]["source_file"]
    for old_bytes, msg in zip(full.transitions, new.of(TRANSITION_TOPIC), strict=True):
        old, t = parse_transition(old_bytes), parse_transition(msg.data)
        assert (t.success, t.reward, t.progress_after) == (old.success, old.reward, old.progress_after)
        assert t.color_before_png == old.color_before_png and t.episode_id == new.episode["episode_id"]
    assert len(new.of("/camera/color")) == len(read_episode(full.path).of("/camera/color"))
    # The script's X is what the heightmaps show (blocks removed, moved or untouched): every rule agrees.
    for rule in ("heightmap", "recorded"):
        code, out, _ = _run(capsys, "mcap", "rescore", str(root), "--out", str(tmp_path / rule), "--json",
                            "--success", rule)
        assert code == 0 and [f["success_changed"] + f["reward_changed"] for f in json.loads(out)["files"]] == [0, 0]


def test_rescore_under_another_reward_changes_exactly_what_it_should(episodes, tmp_path: Path, capsys) -> None:
    root, full, _ = episodes
    (tmp_path / "reward.toml").write_text("[reward]\npick_weight = 0.5\n[learner]\nlr = 0.5\n")
    args = ["mcap", "rescore", str(full.path), "--reward-config", str(tmp_path / "reward.toml"),
            "--set", "reward.push_weight=0", "--out", str(tmp_path / "new"), "--json"]
    code, out, err = _run(capsys, *args)
    assert code == 0, err
    result = json.loads(out)["files"][0]
    new = [parse_transition(m.data) for m in read_episode(result["output"]).of(TRANSITION_TOPIC)]
    expected = [r * (0.5 if p == "pick" else 0.0) for p, r in zip(full.primitives, full.rewards, strict=True)]
    assert [t.reward for t in new] == pytest.approx(expected)
    assert [t.success for t in new] == full.successes
    config = read_episode(result["output"]).config_toml
    assert "pick_weight = 0.5" in config and "push_weight = 0.0" in config
    # Rescoring the same way again names the episode the same: feeding both adds nothing twice.
    code, out, _ = _run(capsys, *args[:-3], "--out", str(tmp_path / "again"), "--json")
    assert json.loads(out)["files"][0]["episode_id"] == result["episode_id"]
    assert rescored_id(result["episode_id"], "0123abcd") == "ep000000.rs-0123abcd"
    code, _, err = _run(capsys, "mcap", "rescore", str(full.path), "--set", "learner.lr=1", "--out", str(tmp_path))
    assert code == 2 and "reward.FIELD=VALUE" in err


def test_heightmap_success_and_rescore_step() -> None:
    res, occ = 0.014, 0.01
    before = np.zeros((SIDE_PX, SIDE_PX), np.float32)
    before[4:8, 4:8] = 0.03
    moved = np.roll(before, 2, axis=1)
    empty = np.zeros_like(before)
    rule = SuccessRule()
    assert heightmap_success("push", before, moved, rule, res, occ, 0.05)
    assert not heightmap_success("push", before, before, rule, res, occ, 0.05)
    assert heightmap_success("pick", before, empty, rule, res, occ, 0.05)
    assert not heightmap_success("pick", before, moved, rule, res, occ, 0.05)  # moved, not removed
    stack1, stack2 = before.copy(), before.copy()
    stack1[4:8, 4:8], stack2[4:8, 4:8] = 0.05, 0.10
    assert heightmap_success("place", stack1, stack2, rule, res, occ, 0.05)
    assert not heightmap_success("place", stack2, stack2, rule, res, occ, 0.05)
    assert area_pixels(1e-4, 0.002) == 25 and area_pixels(1e-4, 0.014) == 1
    everything = SuccessRule("heightmap")
    score = rescore_step("pick", False, before, empty, before, TaskConfig(), RewardConfig(), everything, res)
    assert (score.success, score.progress_before, score.progress_after, score.reward) == (True, 0.0, 1.0, 1.0)
    for rule_ in (SuccessRule("recorded"), SuccessRule("auto")):  # auto: a pick's X is the gripper's
        kept = rescore_step("pick", False, before, empty, before, TaskConfig(), RewardConfig(), rule_, res)
        assert (kept.success, kept.reward) == (False, 0.0)
    push = rescore_step("push", False, before, moved, before, TaskConfig(), RewardConfig(), SuccessRule(), res)
    assert push.success and push.reward == 0.0  # perturbed (X = 1), but the footprint did not shrink: P = 0
    stacking = TaskConfig(kind="stacking", goal_stack_height=2)
    s = rescore_step("place", True, stack1, stack2, stack1, stacking, RewardConfig(), rule, res)
    assert (s.success, s.progress_before, s.progress_after, s.reward) == (True, 0.5, 1.0, 1.0)


def test_playback_delays_follow_recorded_time() -> None:
    opts = PlayOptions(speed=2.0, max_gap_s=5.0)
    assert delay_s(None, 10**9, opts) == 0.0
    assert delay_s(10**9, 2 * 10**9, opts) == pytest.approx(0.5)  # 1 s recorded at 2x
    assert delay_s(0, 60 * 10**9, opts) == pytest.approx(2.5)  # a 60 s pause shortened to 5 s, at 2x
    assert delay_s(2 * 10**9, 10**9, opts) == 0.0  # never backwards
    assert delay_s(0, 10**9, PlayOptions(speed=0)) == 0.0


def test_up_passes_recordings_to_the_learner(tmp_path: Path) -> None:
    import argparse

    from romannet.fleet import ActorLedger
    from romannet.rundir import prepare_run
    from romannet.up import build_specs

    ns = argparse.Namespace(name="off", runs_dir=str(tmp_path), task=None, goal_height=None, actors=0,
                            max_actions=0, resolution=None, robot=None, resume=False, stop_timeout=5.0,
                            config=None, overrides=[], from_recordings=[str(tmp_path)])
    # The learner samples only once the recordings are fed: a ratio limit would hold the feed.
    ns.overrides = ["replay.samples_per_insert=2.0"]
    with pytest.raises(Exception, match=r"replay.samples_per_insert' = 2.0 .*admits \d+ transitions.*"
                                        r"--set replay.samples_per_insert=0"):
        prepare_run(ns)
    assert not (tmp_path / "off").exists()
    ns.overrides = ["replay.samples_per_insert=0"]
    run_dir, cfg = prepare_run(ns)
    specs = {s.name: s for s in build_specs(run_dir, cfg, ns, "tcp/127.0.0.1:1", "tcp/127.0.0.1:2", ActorLedger())}
    assert set(specs) == {"replay", "learner"}
    argv = specs["learner"].argv() if callable(specs["learner"].argv) else specs["learner"].argv
    assert argv[argv.index("--offline") + 1] == str(tmp_path.resolve())
    with pytest.raises(Exception, match="--from-recordings"):
        prepare_run(argparse.Namespace(**{**vars(ns), "name": "x", "from_recordings": [], "actors": 0}))


def test_parse_transition_refuses_garbage() -> None:
    from romannet.common.errors import DecodeError

    with pytest.raises(DecodeError, match="not a protobuf Transition"):
        parse_transition(b"\xff\xff\xff")
