"""The actor loop: reset -> observe -> decide -> execute -> transition -> spool -> sender, episode after episode.

    stats = run_actor(cfg, run_dir, env, replay_client, weights_source, stop_event)

* Decisions use RoManNet through common.policy.InferenceEngine with the newest weights and the learner's
  LAE rate. Both are swapped only between actions (polled right before a decision), never during one; the
  version that chose an action is stamped on its transition. Until the learner's first weights arrive the
  actor acts with its initial weights (RoManNet seeded with cfg.learner.seed: the learner's version 0) and
  cfg.exploration.initial_rate until the first rate arrives, and says so once.
* Every transition is encoded once; the bytes go to the spool (fsync'ed) before the sender thread sends
  them, and into the episode's MCAP file. When the spool is full (replay server down for long) the actor
  pauses before its next action, logs why once, and resumes when acknowledgements make room.
* stop_event (SIGTERM/SIGINT in actor/main.py): the primitive under way finishes, its transition is
  spooled and recorded, the MCAP file is finished, the sender gets actor.shutdown_flush_s to empty the
  spool (the rest stays on disk for the next start), status.json says "stopped".
* Episode ids are `ep<index>` with the index persisted in actors/<id>/state.json before the episode starts,
  so a restarted actor never reuses an id (the replay key (actor_id, episode_id, step) stays unique) and
  scene seeds follow from (cfg.seed, actor_id, index): reproducible, distinct per actor.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
import zlib
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from romannet import __version__
from romannet.common.action import Action, pixel_to_position
from romannet.common.config import Config
from romannet.common.config_actor import ActorConfig
from romannet.common.configbase import dumps_toml
from romannet.common.episode_rules import ideal_actions
from romannet.common.errors import RobotError
from romannet.common.exploration import NonFiniteQError
from romannet.common.failure_memory import FailureMemory
from romannet.common.grasp_clearance import PickClearance
from romannet.common.interfaces import Env, Observation, ReplayClient, StepResult, WeightsSource
from romannet.common.model import RoManNet, state_dict_to_tensors
from romannet.common.policy import InferenceEngine, PolicyMaps, PreparedWeights, decide
from romannet.common.wire import TransitionMsg, encode_transition

from .episode_state import next_episode_index
from .recorder import EpisodeRecorder, step_record
from .scene_frames import scene_frames_of
from .sender import Sender, spool_pause
from .spool import Spool
from .stats import ActorStats, write_status

log = logging.getLogger(__name__)

_PAUSE_POLL_S = 0.25  # how often a paused actor re-checks the spool and the stop event
_QUIET_PAUSE_S = 5.0  # a full spool that drains within this long is not reported as a pause


class Decision(NamedTuple):
    """An action chosen for one observation, the maps it came from, and the weights and rate in force."""

    action: Action
    maps: PolicyMaps
    version: int
    rate: float

    @property
    def value(self) -> float:
        """V of the observation: the largest Q over the nets that ran (those allowed in it)."""
        return max(float(q.max()) for q in self.maps.q.values())


class PendingWeights(NamedTuple):
    """Weights that arrived, being built into nets in the background (InferenceEngine.prepare_async)."""

    version: int
    tensors: Mapping[str, Tensor]
    prepared: Future[PreparedWeights]


@dataclass(frozen=True)
class ActorPaths:
    """Where one actor keeps its files inside the run directory."""

    root: Path  # runs/<run>/actors/<actor_id>
    spool: Path
    episodes: Path  # runs/<run>/episodes/<actor_id>

    @property
    def status(self) -> Path:
        return self.root / "status.json"

    @property
    def resume(self) -> Path:
        """An operator creates this file to resume an actor paused by a robot stop (`touch` it)."""
        return self.root / "resume"

    @property
    def state(self) -> Path:
        return self.root / "state.json"

    @classmethod
    def of(cls, run_dir: str | Path, acfg: ActorConfig) -> ActorPaths:
        run_dir = Path(run_dir)
        root = run_dir / "actors" / acfg.actor_id
        return cls(root, Path(acfg.spool_dir) if acfg.spool_dir else root / "spool",
                   Path(acfg.mcap_dir) if acfg.mcap_dir else run_dir / "episodes" / acfg.actor_id)


def episode_seed(seed: int, actor_id: str, index: int) -> int:
    """Scene seed of an actor's episode `index`: reproducible, different for every actor and episode."""
    return int(np.random.SeedSequence([seed, zlib.crc32(actor_id.encode()), index]).generate_state(1)[0])


class ActorLoop:
    """State of one actor process; run_actor() is the way to use it."""

    def __init__(self, cfg: Config, run_dir: str | Path, env: Env, replay_client: ReplayClient,
                 weights_source: WeightsSource, stop_event: threading.Event, acfg: ActorConfig,
                 engine: InferenceEngine | None = None, demonstrator: Callable[[], Action] | None = None):
        self.cfg, self.acfg, self.env, self.weights, self.stop = cfg, acfg, env, weights_source, stop_event
        # The scripted oracle for the first actor.demo_episodes episodes (actor/main.demonstrator_for).
        self.demonstrator = demonstrator
        self.demonstrating = False  # the episode under way is a demonstration
        self.run_dir = Path(run_dir)
        self.paths = ActorPaths.of(run_dir, acfg)
        self.paths.root.mkdir(parents=True, exist_ok=True)
        self.spool = Spool(self.paths.spool, acfg.spool_max_items, acfg.spool_max_bytes, acfg.spool_fsync)
        self.sender = Sender(self.spool, replay_client, acfg.insert_timeout_s, acfg.resend_backoff_initial_s,
                             acfg.resend_backoff_max_s)
        self.engine = engine or InferenceEngine(RoManNet(cfg.model, seed=cfg.learner.seed), cfg.model,
                                                primitives=cfg.task.primitives)
        self.stats = ActorStats(acfg.actor_id, cfg.run_id, explore_rate=cfg.exploration.initial_rate)
        self.failures = FailureMemory.for_task(cfg)  # of the episode under way
        self.clearance = PickClearance.for_config(cfg)
        # The last weights that produced finite Q maps (None = the initial ones): what a diverged learner's
        # weights are replaced by.
        self.good_weights: tuple[int, dict[str, torch.Tensor]] | None = None
        self.loaded_weights: tuple[int, dict[str, torch.Tensor]] | None = None
        self.config_toml = dumps_toml(cfg)

    # ------------------------------------------------------------------------------------ status
    def write_status(self) -> None:
        s = self.sender.stats()
        status = self.stats.status()
        status.update(spool_items=self.spool.items, spool_bytes=self.spool.bytes,
                      spool_recovered=self.spool.recovered, sent=s.sent, acked=s.acked, accepted=s.accepted,
                      duplicates=s.duplicates, rejected=s.rejected, send_failures=s.failures,
                      server_reachable=s.reachable, paced_inserts=s.paced)
        write_status(self.paths.status, status)

    def limits_reached(self) -> bool:
        a = self.acfg
        return (a.max_actions > 0 and self.stats.actions >= a.max_actions) or \
               (a.episodes > 0 and self.stats.episodes >= a.episodes)

    # ------------------------------------------------------------------------ between actions only
    def swap_policy(self) -> None:
        """Take new weights / exploration rate, if any arrived (called between actions only)."""
        new = self.weights.poll_weights()
        if new is not None:
            version, tensors = new
            self._take_weights(version, tensors, lambda: self.engine.load_state(tensors))
        self.poll_rate()

    def begin_swap(self) -> PendingWeights | None:
        """New weights, if any arrived, prepared on a background thread while the action executes (for an engine
        whose swap costs about a decision: int8); `finish_swap` puts them in force."""
        new = self.weights.poll_weights()
        if new is None:
            return None
        version, tensors = new
        return PendingWeights(version, tensors, self.engine.prepare_async(tensors))

    def finish_swap(self, pending: PendingWeights) -> None:
        self._take_weights(pending.version, pending.tensors, lambda: self.engine.install(pending.prepared.result()))

    def _take_weights(self, version: int, tensors: Mapping[str, Tensor], load: Callable[[], None]) -> None:
        try:
            load()
        except Exception as err:  # weights our model refuses: keep acting with the ones we have
            log.error("weights v%d refused by the model (%s); keeping v%d", version, err,
                      self.stats.weights_version)
        else:
            if self.stats.initial_weights:
                log.info("first weights from the learner: now acting with v%d", version)
            self.stats.weights_version, self.stats.initial_weights = version, False
            self.loaded_weights = (version, tensors)

    def poll_rate(self) -> None:
        rate = self.weights.poll_exploration()
        if rate is not None:
            if not self.stats.explore_rate_received:
                log.info("first exploration rate from the learner: %.3f (%s, v%d)", rate.value, rate.policy,
                         rate.version)
            self.stats.explore_rate, self.stats.explore_rate_received = float(rate.value), True

    def wait_for_spool_room(self) -> bool:
        """Pause while the spool is full; False if stopped while paused."""
        if not self.spool.full():
            return True
        # A short wait is the normal rhythm when the replay's samples-per-insert limit holds acks back
        # until the learner catches up (a small spool then paces the actor): only a longer one is news.
        if self.spool.wait_for_room(_QUIET_PAUSE_S):
            return True
        full = (f"spool full: {self.spool.items} transitions / {self.spool.bytes} bytes not acknowledged "
                f"(bound {self.spool.max_items} items / {self.spool.max_bytes} bytes)")
        kind = self._report_pause(*spool_pause(self.sender.stats(), full))
        started = time.monotonic()
        while not self.spool.wait_for_room(_PAUSE_POLL_S):
            if self.stop.is_set():
                return False
            now_kind, reason = spool_pause(self.sender.stats(), full)
            if now_kind != kind:  # e.g. the insert in flight timed out: now an outage, and news
                kind = self._report_pause(now_kind, reason)
        log.log(logging.DEBUG if kind == "paced" else logging.INFO,
                "actor resumed after %.1f s paused: the spool has room again (%d items)",
                time.monotonic() - started, self.spool.items)
        self.stats.paused, self.stats.pause_kind, self.stats.pause_reason = False, "", ""
        self.stats.state = "running"
        self.write_status()
        return True

    def _report_pause(self, kind: str, reason: str) -> str:
        """Log a spool pause at the level its kind deserves, put it in the status; returns kind."""
        level = {"paced": logging.DEBUG, "waiting": logging.INFO}.get(kind, logging.WARNING)
        log.log(level, "actor %s: %s", "paused" if kind == "outage" else "waiting", reason)
        self.stats.paused, self.stats.pause_kind, self.stats.pause_reason = True, kind, reason
        self.stats.state = "paused"
        self.write_status()
        return kind

    def wait_for_operator(self) -> bool:
        """While the environment is paused (a real robot stopped), wait for an operator; False if stopped.

        The robot never moves by itself after a stop: an operator clears it on the teach pendant, makes the
        cell safe, then creates the resume file; the environment then checks the controller is ready.
        """
        reason = self.env.paused
        if not reason:
            return True
        self.paths.resume.unlink(missing_ok=True)  # a request from before this stop does not count
        message = f"{reason}. To resume: touch {self.paths.resume}"
        log.error("actor paused: %s", message)
        self.stats.paused, self.stats.pause_kind, self.stats.pause_reason = True, "robot", message
        self.stats.state = "paused"
        self.write_status()
        while not self.stop.is_set():
            if self.paths.resume.exists():
                self.paths.resume.unlink(missing_ok=True)
                if self.env.try_resume():
                    log.info("actor resumed by the operator")
                    self.stats.paused, self.stats.pause_kind, self.stats.pause_reason = False, "", ""
                    self.stats.state = "running"
                    self.write_status()
                    return True
                log.error("resume refused: the robot is not ready yet (see above); still paused. %s", message)
            self.stop.wait(_PAUSE_POLL_S)
        return False

    # ----------------------------------------------------------------------------------- episodes
    def run(self) -> ActorStats:
        self.sender.start()
        log.info("actor %s: acting with initial weights (v0, seed %d) until the learner's first weights "
                 "arrive, exploration rate %.3f until its first rate arrives", self.acfg.actor_id,
                 self.cfg.learner.seed, self.stats.explore_rate)
        self.stats.state = "running"
        self.write_status()
        try:
            while not self.stop.is_set() and not self.limits_reached():
                if not self.wait_for_operator():
                    break
                try:
                    self.run_episode()
                except RobotError as err:  # a robot stop before the episode's first action: pause, not crash
                    if not self.env.paused:
                        raise
                    log.error("the episode could not start: %s", err)
        finally:
            self.stats.state = "stopping"
            self.write_status()
            self.sender.stop(self.acfg.shutdown_flush_s)
            self.stats.state = "stopped"
            self.write_status()
            self.engine.close()
            s = self.sender.stats()
            log.info("actor %s stopped: %d actions, %d episodes (%d completed), picks %d/%d, weights versions "
                     "used %d, acked %d, left in spool %d", self.acfg.actor_id, self.stats.actions,
                     self.stats.episodes, self.stats.completed_episodes, self.stats.successful_picks,
                     self.stats.picks, len(self.stats.versions_used), s.acked, self.spool.items)
        return self.stats

    def run_episode(self) -> None:
        index = next_episode_index(self.paths.state, self.paths.episodes)
        episode_id = f"ep{index:06d}"
        seed = episode_seed(self.cfg.seed, self.acfg.actor_id, index)
        self.demonstrating = self.demonstrator is not None and index < self.acfg.demo_episodes
        # Exploration draws: reproducible per (seed, actor, episode), independent of the scene's generator.
        rng = np.random.default_rng([self.cfg.seed, zlib.crc32(self.acfg.actor_id.encode()), index, 1])
        obs = self.env.reset(seed)
        self.failures.reset()
        self.stats.episode_id, self.stats.episode_step = episode_id, 0
        recorder = None
        if self.acfg.record_mcap:
            recorder = EpisodeRecorder(
                self.paths.episodes / f"{episode_id}.mcap",
                {"run_id": self.cfg.run_id, "actor_id": self.acfg.actor_id, "episode_id": episode_id,
                 "task": self.cfg.task.kind, "seed": seed, "weights_version_start": self.stats.weights_version,
                 "initial_weights": self.stats.initial_weights, "explore_rate_start": self.stats.explore_rate,
                 "demonstration": self.demonstrating,
                 "romannet_version": __version__},
                self.config_toml, self.acfg.mcap_chunk_bytes, self.acfg.mcap_compression,
                self.acfg.record_camera, self.acfg.camera_color_format, self.acfg.jpeg_quality,
                scene=scene_frames_of(self.env, self.cfg))
        done_reason, ep_picks, ep_actions = "stopped", 0, 0
        try:
            if recorder is not None:
                recorder.write_observation(obs, time.time_ns())
            step = 0
            decision: Decision | None = None  # taken for `obs` when the previous action's value was read
            while True:
                if self.stop.is_set() or self.limits_reached() or not self.wait_for_spool_room():
                    done_reason = "max_actions" if self.limits_reached() else "stopped"
                    break
                if decision is None:
                    self.swap_policy()
                    decision = self.decision(obs, rng)
                primitive, result, decision = self.act(obs, decision, episode_id, step, rng, recorder)
                ep_actions += 1
                ep_picks += int(primitive == "pick" and result.success)
                obs, step = result.observation, step + 1
                if result.done:
                    done_reason = result.done_reason
                    break
        finally:
            efficiency = None
            if done_reason == "done" and ep_actions:
                ideal = ideal_actions(self.cfg.task.kind, ep_picks, self.cfg.task.goal_stack_height)
                efficiency = min(1.0, ideal / ep_actions)
            if recorder is not None:
                recorder.close({"done_reason": done_reason, "steps": recorder.steps, "efficiency": efficiency,
                                "weights_version_end": self.stats.weights_version})
            if done_reason not in ("stopped", "max_actions"):
                self.stats.record_episode_end(done_reason, efficiency)
            else:
                self.stats.last_done_reason = done_reason
            self.write_status()
            log.info("%s %s (seed %d) ended: %s after %d actions; weights v%d, rate %.3f, spool %d",
                     "demonstration" if self.demonstrating else "episode", episode_id, seed, done_reason,
                     ep_actions, self.stats.weights_version, self.stats.explore_rate, self.spool.items)

    def decide(self, obs: Observation, rng: np.random.Generator) -> tuple[Action, PolicyMaps]:
        """RoManNet's decision; weights whose Q maps are not finite are dropped for the last good ones."""
        args = (obs.color_hm, obs.depth_hm, obs.holding, self.stats.explore_rate, rng, self.env.primitives,
                self.cfg.exploration)
        try:
            result = decide(self.engine, *args, return_maps=True, avoid=self.failures,
                            clearance=self.clearance)
        except NonFiniteQError as err:
            if self.loaded_weights is None:  # the initial weights themselves: nothing to fall back to
                raise
            bad = self.loaded_weights[0]
            if self.good_weights is None:
                good, tensors = 0, state_dict_to_tensors(RoManNet(self.cfg.model, seed=self.cfg.learner.seed))
            else:
                good, tensors = self.good_weights
            log.error("weights v%d give non-finite Q maps (%s: has the learner diverged?); back to v%d until "
                      "newer weights arrive", bad, err, good)
            self.engine.load_state(tensors)
            self.loaded_weights, self.stats.weights_version = self.good_weights, good
            self.stats.initial_weights = self.good_weights is None
            result = decide(self.engine, *args, return_maps=True, avoid=self.failures,
                            clearance=self.clearance)
        self.good_weights = self.loaded_weights
        return result

    def decision(self, obs: Observation, rng: np.random.Generator) -> Decision:
        """The next action for `obs` with the weights and rate in force now; in a demonstration the oracle's
        action (the policy's Q maps still give the transition's V(s_{t+1}) for the bootstrap)."""
        action, maps = self.decide(obs, rng)
        if self.demonstrating:
            action = dataclasses.replace(self.demonstrator(), explored=True)
        return Decision(action, maps, self.stats.weights_version, self.stats.explore_rate)

    def act(self, obs: Observation, decision: Decision, episode_id: str, step: int, rng: np.random.Generator,
            recorder: EpisodeRecorder | None) -> tuple[str, StepResult, Decision | None]:
        """Execute a decision, take the next one (its Q maps give the transition's V(s_{t+1}), which the
        learner then need not compute), then spool, record and count the action.

        Returns (primitive, result, the decision for the next observation or None at the episode's end)."""
        start_ns = time.time_ns()
        action, maps, version, rate = decision
        q_ranges = recorder.write_q_maps(maps.q, start_ns) if recorder is not None else {}
        pending = self.begin_swap() if self.engine.slow_swap else None
        try:
            result = self.env.step(action)
            end_ns = max(time.time_ns(), start_ns)
        finally:  # in force even if the step failed: the weights source hands each version out once
            if pending is not None:
                self.finish_swap(pending)
        # before the next decision, which avoids it
        self.failures.record(action, result.success, result.progress_before, result.progress_after)
        following = None
        if not result.done and not self.stop.is_set() and not self._last_action():
            if self.engine.slow_swap:  # weights that came during the action: prepared during the next one
                self.poll_rate()
            else:
                self.swap_policy()
            following = self.decision(result.observation, rng)
        msg = TransitionMsg.from_step(
            obs, action, result, actor_id=self.acfg.actor_id, episode_id=episode_id, step=step,
            start_ns=start_ns, end_ns=end_ns, task=self.cfg.task.kind, policy_version=version, explore_rate=rate,
            initial_priority=self.acfg.priority_for(result.reward),
            next_value=following.value if following is not None else None,
            next_value_version=following.version if following is not None else None)
        data = encode_transition(msg)
        self.spool.put(data)  # durable before anything else: from here on it cannot be lost
        self.stats.record_action(action.primitive, result.success, version)
        if recorder is not None:
            position_m = list(pixel_to_position(action.row, action.col, obs.depth_hm, self.cfg.workspace))
            record = step_record(msg, position_m, result.detail, q_ranges, result.info)
            recorder.write_observation(result.observation, end_ns)
            recorder.write_step(data, record, end_ns)  # flushes the step's chunk, observation included
        self.write_status()
        return action.primitive, result, following

    def _last_action(self) -> bool:
        """The action under way is the last this process may take (its max_actions)."""
        return self.acfg.max_actions > 0 and self.stats.actions + 1 >= self.acfg.max_actions


def run_actor(cfg: Config, run_dir: str | Path, env: Env, replay_client: ReplayClient,
              weights_source: WeightsSource, stop_event: threading.Event, actor_cfg: ActorConfig | None = None,
              engine: InferenceEngine | None = None,
              demonstrator: Callable[[], Action] | None = None) -> ActorStats:
    """Run the actor loop until stop_event is set or actor.max_actions / actor.episodes is reached.

    actor_cfg defaults to cfg.actor; engine (for tests) defaults to one built from cfg.model. The caller
    owns env, replay_client and weights_source (and closes them); the spool, sender and engine are closed here.
    demonstrator: the action for the current state in the first actor.demo_episodes episodes
    (main.demonstrator_for).
    """
    loop = ActorLoop(cfg, run_dir, env, replay_client, weights_source, stop_event,
                     actor_cfg or cfg.actor, engine, demonstrator)
    return loop.run()
