"""A run's own training curves: episodes written by the real recorder, read back into curves, drawn as a PNG
with its five panels, and written as TensorBoard events read back with TensorBoard's EventAccumulator."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams import metadata as hp_metadata
from tensorboard.plugins.hparams import plugin_data_pb2

from romannet.actor.recorder import EpisodeRecorder
from romannet.common.config import load_config
from romannet.common.configbase import write_toml
from romannet.evaluate.run_board import ACTION_TAGS, EPISODE_TAGS
from romannet.evaluate.run_curves import actions_rate, rolling_mean
from romannet.evaluate.run_figure import PANELS
from romannet.evaluate.run_report import BOARD_DIR, PNG_NAME, RunReport

S = 10**9  # one second in ns


def record(run_dir: Path, actor: str, name: str, steps: list[tuple[float, bool, float]], end: str | None) -> None:
    """An episode file as an actor writes it: (time s, success, reward) per step; `end` is the last step's
    done reason (None: the episode is still under way)."""
    rec = EpisodeRecorder(run_dir / "episodes" / actor / f"{name}.mcap", {"run_id": "r", "actor_id": actor})
    for i, (t_s, success, reward) in enumerate(steps):
        last = i == len(steps) - 1
        rec.write_step(b"\x00" * 8, {"step": i, "primitive": "pick", "success": success, "reward": reward,
                                     "done": last and end is not None, "done_reason": end if last and end else "",
                                     "info": {"objects_in_workspace": 3}}, int(t_s * S))
    rec.close()


def make_run(tmp_path: Path) -> Path:
    run_dir = tmp_path / "demo"
    write_toml(load_config(None, ['run_id="demo"', "task.kind=clutter"]), run_dir / "config.toml")
    # Two actors, interleaved in time: actions at 1..9 s (a0: 1, 2, 3 | 6, 7; a1: 4, 5 | 8, 9 still running).
    record(run_dir, "a0", "ep0", [(1, True, 1.0), (2, False, 0.0), (3, True, 0.5)], "done")
    record(run_dir, "a1", "ep0", [(4, False, -0.5), (5, False, 0.0)], "step_limit")
    record(run_dir, "a0", "ep1", [(6, True, 1.0), (7, True, 1.0)], "done")
    record(run_dir, "a1", "ep1", [(8, True, 0.25), (9, False, 0.0)], None)
    return run_dir


def test_pure_helpers() -> None:
    assert rolling_mean(np.array([1.0, 0.0, 1.0, 1.0]), 2).tolist() == [1.0, 0.5, 0.5, 1.0]
    rate = actions_rate(np.array([0, 1, 2, 4], dtype=np.int64) * S, 2)
    assert np.isnan(rate[0]) and rate[1:].tolist() == [1.0, 1.0, pytest.approx(2 / 3)]


def test_curves_of_recorded_episodes(tmp_path: Path) -> None:
    curves = RunReport(make_run(tmp_path), window=4, episode_window=2, board=False).curves()
    assert curves.actions == 9 and curves.episodes == 3 and curves.completed == 2
    assert curves.episode_x.tolist() == [3, 5, 7]  # actions of every actor taken by each episode's end
    assert curves.episode_return.tolist() == [1.5, -0.5, 2.0]
    assert curves.episode_length.tolist() == [3, 2, 2]
    assert curves.completion_rate.tolist() == [1.0, 0.5, 0.5]
    # Successes by time: T F T F F T T T F; the window of 4 from the 4th action on.
    assert curves.action_x.tolist() == [4, 5, 6, 7, 8, 9]
    assert curves.success_rate.tolist() == [0.5, 0.25, 0.5, 0.5, 0.75, 0.75]
    assert curves.actions_per_s.tolist() == pytest.approx([1.0] * 6)  # one action a second


def _dark_rows(png: Path) -> int:
    """Horizontal axis lines in a PNG: runs of rows more than half of whose pixels are dark."""
    gray = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    dark = (gray < 100).mean(axis=1) > 0.5
    return int(np.sum(dark[1:] & ~dark[:-1]) + dark[0])


def test_png_has_five_panels_and_the_board_reads_back(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path)
    report = RunReport(run_dir, window=4, episode_window=2)
    curves = report.refresh()
    png = run_dir / PNG_NAME
    assert _dark_rows(png) == 2 * len(PANELS)  # each panel's top and bottom frame line
    # A new episode ends; the next refresh adds only what is new.
    record(run_dir, "a0", "ep2", [(10, True, 1.0)], "done")
    report.refresh()
    report.close()
    board = run_dir.joinpath(*BOARD_DIR)
    acc = EventAccumulator(str(board), size_guidance={"tensors": 0, "scalars": 0})
    acc.Reload()
    assert set(acc.Tags()["scalars"]) == {*ACTION_TAGS, *EPISODE_TAGS}
    returns = [(e.step, e.value) for e in acc.Scalars("episodes/return")]
    assert returns == [(3, 1.5), (5, -0.5), (7, 2.0), (10, 1.0)]  # each episode once, at its action count
    assert [e.step for e in acc.Scalars("episodes/completion_rate")] == [3, 5, 7, 10]
    steps = [e.step for e in acc.Scalars("actions/success_rate")]
    assert steps == sorted(set(steps)) and steps[0] == curves.action_x[0]
    text = acc.Tensors("config")[0].tensor_proto.string_val[0].decode()
    assert [line[4:] for line in text.splitlines()] == (run_dir / "config.toml").read_text().splitlines()
    content = acc.PluginTagToContent(hp_metadata.PLUGIN_NAME)
    start = plugin_data_pb2.HParamsPluginData.FromString(content[hp_metadata.SESSION_START_INFO_TAG])
    assert start.session_start_info.hparams["task.kind"].string_value == "clutter"
    assert start.session_start_info.hparams["seed"].number_value == 0
    experiment = plugin_data_pb2.HParamsPluginData.FromString(content[hp_metadata.EXPERIMENT_TAG]).experiment
    assert {m.name.tag for m in experiment.metric_infos} == {*ACTION_TAGS, *EPISODE_TAGS}
    # A resumed run's launcher writes the whole history again into one fresh file.
    RunReport(run_dir, window=4, episode_window=2).refresh()
    assert len(list(board.glob("events.out.tfevents.*"))) == 1
    acc = EventAccumulator(str(board))
    acc.Reload()
    assert [e.step for e in acc.Scalars("episodes/return")] == [3, 5, 7, 10]


def test_plot_verb_draws_one_run_and_refuses_a_non_run(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path)
    out = tmp_path / "one.png"
    romannet = [sys.executable, "-m", "romannet.cli", "plot"]
    proc = subprocess.run([*romannet, str(run_dir), "--window", "4", "--out", str(out)], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["actions"] == 9 and summary["episodes"] == 3 and summary["completed"] == 2
    assert summary["final_success_rate"] == 0.75 and summary["final_completion_rate"] == pytest.approx(2 / 3)
    assert _dark_rows(out) == 2 * len(PANELS)
    assert not run_dir.joinpath(*BOARD_DIR).exists()  # plot draws; only a run's launcher writes its events
    proc = subprocess.run([*romannet, str(tmp_path), "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "no config.toml" in proc.stderr


def test_live_report_redraws_while_running_and_ends_with_every_episode(tmp_path: Path, caplog) -> None:
    """The launcher's thread: redrawn while episodes arrive, a broken file a warning, all of it at close."""
    import time

    from romannet.evaluate.run_report import LiveRunReport

    run_dir = make_run(tmp_path)
    live = LiveRunReport(run_dir, window=4, every_s=0.05)
    deadline = time.monotonic() + 60
    while not (run_dir / PNG_NAME).exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (run_dir / PNG_NAME).exists()
    (run_dir / "episodes" / "a1" / "junk.mcap").write_bytes(b"not an episode")
    record(run_dir, "a1", "ep1", [(8, True, 0.25), (9, False, 0.0), (11, True, 1.0)], "done")  # a1 finishes
    live.close()
    acc = EventAccumulator(str(run_dir.joinpath(*BOARD_DIR)))
    acc.Reload()
    assert [e.step for e in acc.Scalars("episodes/return")] == [3, 5, 7, 10]
    assert acc.Scalars("episodes/return")[-1].value == pytest.approx(1.25)
    assert "junk.mcap skipped" in caplog.text
