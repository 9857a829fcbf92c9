"""`romannet mcap rescore FILE|DIR`: X, P and rewards recomputed from the recorded heightmaps under another
reward configuration, written as new episode files (--out DIR) and/or fed to a replay server (--feed).

The reward configuration is the one recorded in each file, then the [reward] table of --reward-config,
then --set reward.FIELD=VALUE. X follows --success (rescoring.py beside this file): by default push and
place are judged from the heightmaps and pick as the gripper recorded it. P and R_tp follow common/reward.py exactly.

A rescored episode is a new episode: its id is the source's plus `.rs-<8 hex>`, a digest of the reward
configuration and the X rule, so rescored and original experience can share a replay server, and
rescoring the same files the same way again gives the same ids (feeding them twice adds nothing). Each
output file is the source file with its /transition and /step messages rewritten (everything else,
images and Q maps included, is copied as is), its config metadata carrying the new [reward] section and a
"rescore" metadata record naming the source and the rule. Output layout: OUT/<run>/<actor>/<episode>.mcap;
ids that could leave OUT (common/safe_names.py) make the file an error of its own, the others go on.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomllib

from romannet.common import romannet_pb2 as pb
from romannet.common.config import Config, RewardConfig
from romannet.common.configbase import apply_overrides, dumps_toml, from_dict, read_toml, to_dict
from romannet.common.episode_file import (
    CONFIG_METADATA,
    END_METADATA,
    EPISODE_METADATA,
    HEIGHTMAP_DEPTH_TOPIC,
    STEP_TOPIC,
    TRANSITION_TOPIC,
    EpisodeFileError,
    EpisodeReader,
    RecordedMessage,
)
from romannet.common.errors import ConfigError, RomannetError
from romannet.common.imagecodec import units_to_depth_m
from romannet.common.safe_names import UnsafeNameError, safe_name
from romannet.common.wire import decode_transition

from .render import decode_raw16
from .rescoring import Score, SuccessRule, rescore_step
from .rewrite import EpisodeWriter

log = logging.getLogger(__name__)

_SUFFIX_RE = re.compile(r"\.rs-[0-9a-f]{8}$")
_KERNEL_FIELDS = ("use_gaussian", "sigma_y_px", "anisotropy", "kernel_normalization", "kernel_radius_sigmas")


@dataclass(frozen=True)
class RescoreSettings:
    """What changes: reward_table and overrides apply on top of each file's recorded [reward]."""

    reward_table: dict[str, Any] = field(default_factory=dict)
    overrides: tuple[str, ...] = ()  # "reward.FIELD=VALUE"
    rule: SuccessRule = SuccessRule()

    def __post_init__(self) -> None:
        for text in self.overrides:
            if not text.strip().startswith("reward."):
                raise ConfigError(text.split("=")[0], text, "rescore changes the reward only: use --set "
                                  "reward.FIELD=VALUE, e.g. --set reward.push_weight=0.5")

    def reward(self, recorded: RewardConfig) -> RewardConfig:
        data = {"reward": {**to_dict(recorded), **self.reward_table}}
        return from_dict(RewardConfig, apply_overrides(data, list(self.overrides))["reward"], prefix="reward")


def load_reward_table(path: str | Path) -> dict[str, Any]:
    """The [reward] table of a TOML file (a whole fleet config works; its other sections are ignored)."""
    table = read_toml(path).get("reward")
    if not isinstance(table, dict):
        raise ConfigError("--reward-config", str(path), "the file has no [reward] table")
    return table


def digest(reward: RewardConfig, rule: SuccessRule) -> str:
    """8 hex digits naming a (reward configuration, X rule) pair."""
    text = json.dumps({"reward": to_dict(reward), "success": dataclasses.asdict(rule)}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def rescored_id(episode_id: str, tag: str) -> str:
    """`<episode_id>.rs-<tag>`, replacing an earlier rescore's suffix."""
    return f"{_SUFFIX_RE.sub('', episode_id)}.rs-{tag}"


@dataclass
class FileResult:
    """What rescoring one file did."""

    source: str
    output: str | None
    episode_id: str
    steps: int = 0
    success_changed: int = 0
    reward_changed: int = 0
    reward_sum_recorded: float = 0.0
    reward_sum: float = 0.0
    truncated: bool = False
    transitions: list[bytes] = field(default_factory=list, repr=False)  # the new transitions, for --feed

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in self.__dict__.items() if k != "transitions"}
        out["reward_sum_recorded"] = round(self.reward_sum_recorded, 6)
        out["reward_sum"] = round(self.reward_sum, 6)
        return out


class _Episode:
    """State of one file being rescored."""

    def __init__(self, reader: EpisodeReader, settings: RescoreSettings):
        if not reader.config_toml:
            raise RomannetError(f"{reader.path}: no recorded config: rescoring needs its task and workspace")
        try:
            self.cfg = from_dict(Config, tomllib.loads(reader.config_toml))
        except (tomllib.TOMLDecodeError, ValueError) as err:
            raise RomannetError(f"{reader.path}: the recorded config does not load: {err}") from None
        self.reward = settings.reward(self.cfg.reward)
        self.rule = settings.rule
        self.tag = digest(self.reward, self.rule)
        self.source_id = _recorded_name(reader.path, reader.episode, "episode_id", reader.path.stem)
        self.episode_id = rescored_id(self.source_id, self.tag)
        self.depth_start: np.ndarray | None = None
        self.last: tuple[Score, pb.Transition] | None = None

    def transition(self, data: bytes) -> tuple[bytes, Score, pb.Transition]:
        msg = decode_transition(data)  # validated, pixels decoded
        if self.depth_start is None:
            self.depth_start = msg.depth_before
        score = rescore_step(msg.action.primitive, msg.success, msg.depth_before, msg.depth_after,
                             self.depth_start, self.cfg.task, self.reward, self.rule,
                             self.cfg.workspace.resolution_m)
        t = pb.Transition()
        t.ParseFromString(data)
        recorded = pb.Transition()
        recorded.CopyFrom(t)
        t.episode_id = self.episode_id
        t.success, t.reward = score.success, score.reward
        t.progress_before, t.progress_after = score.progress_before, score.progress_after
        if t.HasField("initial_priority"):
            priority = self.cfg.actor.priority_for(score.reward)
            if priority is None:
                t.ClearField("initial_priority")
            else:
                t.initial_priority = priority
        return t.SerializeToString(), score, recorded

    def step_record(self, data: bytes) -> bytes:
        try:
            record = json.loads(data)
        except ValueError:
            return data
        if self.last is None or not isinstance(record, dict):
            return data
        score, recorded = self.last
        record.update(episode_id=self.episode_id, success=score.success, reward=score.reward,
                      progress_before=score.progress_before, progress_after=score.progress_after,
                      rescored={"success_recorded": recorded.success, "reward_recorded": recorded.reward,
                                "progress_after_recorded": recorded.progress_after, "tag": self.tag})
        return json.dumps(record).encode()

    def metadata(self, reader: EpisodeReader) -> dict[str, dict[str, str]]:
        episode = {**reader.episode, "episode_id": self.episode_id}
        config = dataclasses.replace(self.cfg, reward=self.reward)
        rescore = {"source_file": reader.path.name, "source_episode_id": self.source_id, "tag": self.tag,
                   "success_rule": json.dumps(dataclasses.asdict(self.rule)),
                   "reward": json.dumps(to_dict(self.reward))}
        return {EPISODE_METADATA: episode, CONFIG_METADATA: {"toml": dumps_toml(config)}, "rescore": rescore}


def _recorded_name(path: Path, episode: dict[str, str], key: str, default: str) -> str:
    """The episode metadata's `key` (default if absent), checked before it names a file or a directory."""
    try:
        return safe_name(episode.get(key, default), f"metadata {key}")
    except UnsafeNameError as err:
        raise EpisodeFileError(path, str(err)) from None


def output_path(out_dir: Path, reader: EpisodeReader, episode_id: str) -> Path:
    """OUT/<run>/<actor>/<episode_id>.mcap, every component checked: a crafted file cannot leave out_dir."""
    run = _recorded_name(reader.path, reader.episode, "run_id", "run")
    actor = _recorded_name(reader.path, reader.episode, "actor_id", "actor")
    return out_dir / run / actor / f"{episode_id}.mcap"


def _depth_of(msg: RecordedMessage) -> np.ndarray:
    return units_to_depth_m(decode_raw16(msg.data))


def _rescored_messages(reader: EpisodeReader, make: Callable[[EpisodeReader], _Episode],
                       result: FileResult) -> Iterator[tuple[_Episode, RecordedMessage, bytes | None]]:
    """(episode state, message, new bytes or None) for every message of the file, in order."""
    ep: _Episode | None = None
    for msg in reader.messages():
        if ep is None:
            ep = make(reader)  # the metadata precedes every message
        if msg.topic == HEIGHTMAP_DEPTH_TOPIC and ep.depth_start is None:
            ep.depth_start = _depth_of(msg)  # the episode's first heightmap: P's reference (clutter)
        new = None
        if msg.topic == TRANSITION_TOPIC:
            new, score, recorded = ep.transition(msg.data)
            ep.last = (score, recorded)
            result.steps += 1
            result.success_changed += int(score.success != recorded.success)
            result.reward_changed += int(abs(score.reward - recorded.reward) > 1e-9)
            result.reward_sum_recorded += recorded.reward
            result.reward_sum += score.reward
            result.transitions.append(new)
        elif msg.topic == STEP_TOPIC:
            new = ep.step_record(msg.data)
        yield ep, msg, new


def rescore_file(path: str | Path, settings: RescoreSettings, out_dir: Path | None) -> FileResult:
    """Rescore one episode file; writes OUT/<run>/<actor>/<new id>.mcap when out_dir is given."""
    reader = EpisodeReader(path)
    result = FileResult(str(path), None, "")
    ep: _Episode | None = None
    with contextlib.ExitStack() as stack:  # an exception removes the half-written output
        writer: EpisodeWriter | None = None
        for ep, msg, new in _rescored_messages(reader, lambda r: _Episode(r, settings), result):
            if writer is None and out_dir is not None:
                target = output_path(out_dir, reader, ep.episode_id)
                if target.resolve() == Path(path).resolve():
                    raise RomannetError(f"{path}: --out would overwrite the source file")
                writer = stack.enter_context(EpisodeWriter(target, ep.metadata(reader),
                                                           library="romannet mcap rescore"))
                result.output = str(target)
            if writer is not None:
                channel = reader.channel_by_topic(msg.topic)
                assert channel is not None
                writer.write(channel, msg, new)
        if writer is not None and END_METADATA in reader.metadata:
            writer.add_metadata(END_METADATA, reader.metadata[END_METADATA])
    result.episode_id = ep.episode_id if ep is not None else ""
    result.truncated = reader.health is None or not reader.health.complete or reader.health.damaged
    return result


def touches_kernel(settings: RescoreSettings) -> bool:
    """True if the settings change a TPG kernel field (which shapes labels, not the recorded R_tp)."""
    named = set(settings.reward_table) | {o.split("=")[0].strip().removeprefix("reward.") for o in settings.overrides}
    return bool(named & set(_KERNEL_FIELDS))
