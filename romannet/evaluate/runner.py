"""One evaluation run in a worker process: fresh scene from a seed, greedy RoManNet (or the scripted oracle,
or random valid actions: policies.py), until the task ends.

Protocols (the paper's "Evaluation Metrics"):
  frozen  the checkpoint's weights, no learning at all.
  paper   as the paper and the authors' (VPG-derived) code test: the weights are reset to the checkpoint
          at the start of every run, and after every action the network takes one SGD step on that action's
          transition (batch of one, the learner's loss, optimiser settings and target), so it can learn
          within the run; the next decision uses the updated weights. The optimiser's momentum is reset
          with the weights.
The oracle and random policies have no weights and never learn: they always run as frozen.

A worker keeps its simulator, inference engine and trainer between runs (rebuilt only when the task
changes), so a run costs its actions, not start-up. Everything here is per process: one worker, one
PyBullet client, one torch thread pool of `threads` threads.
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.oracle import oracle_action
from romannet.actor.sim.tasks import objects_in_workspace
from romannet.common.action import Action
from romannet.common.config import Config, load_config_text
from romannet.common.episode_rules import ideal_actions
from romannet.common.failure_memory import FailureMemory
from romannet.common.grasp_clearance import PickClearance
from romannet.common.interfaces import Observation, StepResult
from romannet.common.model import RoManNet, load_tensors
from romannet.common.policy import InferenceEngine, decide
from romannet.common.wire_messages import TransitionMsg
from romannet.learner.trainer import Trainer

from .metrics import RunLog, StepLog
from .policies import random_action
from .policy_names import POLICIES

log = logging.getLogger(__name__)

PROTOCOLS = ("paper", "frozen")
ENV_MAX_STEPS = 10000  # the run's own step limit (RunSpec.max_steps) ends it first


@dataclass(frozen=True)
class EvalSetup:
    """What every run of one evaluation shares (sent to each worker once)."""

    config_toml: str  # the resolved config the checkpoint was trained with, plus the eval's overrides
    checkpoint: str  # a ckpt-* directory holding tensors.safetensors ("" for the oracle and random policies)
    protocol: str  # "paper" or "frozen"
    threads: int = 1  # torch threads per worker
    policy: str = "net"  # one of policies.POLICIES

    def __post_init__(self) -> None:
        if self.policy not in POLICIES:
            raise ValueError(f"unknown policy {self.policy!r}: expected one of {', '.join(POLICIES)}")
        if self.policy == "net" and not self.checkpoint:
            raise ValueError("the net policy needs a checkpoint")

    @property
    def learning(self) -> bool:
        """Whether runs learn within themselves (the paper protocol on a net)."""
        return self.policy == "net" and self.protocol == "paper"


@dataclass(frozen=True)
class RunSpec:
    """One run: which case, which seed, which task variant."""

    case: str  # name in the report: "clutter", "h4", or the arrangement case's file stem
    seed: int
    task: str  # clutter | arrangement | stacking
    goal_height: int = 4  # stacking
    num_objects: int = 30  # clutter
    object_set: str = "blocks"  # clutter
    case_file: str = ""  # arrangement
    max_steps: int = 150


def run_config(base: Config, spec: RunSpec) -> Config:
    """The config of one run: the base with the spec's task, goal, objects or case file applied."""
    task = dataclasses.replace(base.task, kind=spec.task, goal_stack_height=spec.goal_height)
    sim = dataclasses.replace(base.sim, max_steps=ENV_MAX_STEPS)
    if spec.task == "clutter":
        sim = dataclasses.replace(sim, num_objects=spec.num_objects, object_set=spec.object_set)
    elif spec.task == "arrangement":
        sim = dataclasses.replace(sim, case_file=spec.case_file)
    return dataclasses.replace(base, task=task, sim=sim)


def load_model_tensors(checkpoint: str | Path) -> dict[str, torch.Tensor]:
    """The online net's tensors of a checkpoint directory, verified (learner/ckpt_integrity.py; no pickle)."""
    from romannet.learner.ckpt_integrity import read_verified

    return read_verified(checkpoint).model_tensors()


class Worker:
    """A worker process's simulator, policy and (paper protocol) trainer, reused across runs."""

    def __init__(self, setup: EvalSetup):
        torch.set_num_threads(max(1, setup.threads))
        self.setup = setup
        self.base = load_config_text(setup.config_toml)
        self.weights: dict[str, torch.Tensor] = {}
        self.engine: InferenceEngine | None = None
        if setup.policy == "net":
            self.weights = load_model_tensors(setup.checkpoint)
            self.engine = InferenceEngine(RoManNet(self.base.model), self.base.model,
                                          parallel_nets=setup.threads >= 2)
            self.engine.load_state(self.weights)
        self._env: SimEnv | None = None
        self._env_key: tuple | None = None
        self._trainer: Trainer | None = None
        self._trainer_key: object = None

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
        if self.engine is not None:
            self.engine.close()

    def env(self, cfg: Config) -> SimEnv:
        key = (cfg.task, cfg.sim)
        if self._env is None or self._env_key != key:
            if self._env is not None:
                self._env.close()
            self._env, self._env_key = SimEnv.from_config(cfg), key
        return self._env

    def trainer(self, cfg: Config) -> Trainer:
        """A trainer for cfg's task whose weights and optimiser are reset to the checkpoint."""
        if self._trainer is None or self._trainer_key != cfg.task:
            self._trainer = Trainer(cfg.model, cfg.learner, cfg.reward, cfg.task, exploration_cfg=cfg.exploration)
            self._trainer_key = cfg.task
        t = self._trainer
        load_tensors(t.model, self.weights)
        t.model.train()
        t.optimizer.state.clear()  # momentum restarts with the weights
        return t

    def act(self, env: SimEnv, obs: Observation, cfg: Config, rng: np.random.Generator,
            memory: FailureMemory) -> Action:
        """The next action of this evaluation's policy (the trained one avoids the run's failures as an
        actor does, exploration.failure_memory_px)."""
        if self.engine is not None:
            return decide(self.engine, obs.color_hm, obs.depth_hm, obs.holding, 0.0, rng, env.primitives,
                          cfg.exploration, avoid=memory, clearance=PickClearance.for_config(cfg))
        if self.setup.policy == "oracle":
            return oracle_action(env)
        rule = PickClearance.for_config(cfg)
        clear = rule.clear(obs.depth_hm) if rule is not None and not obs.holding else None
        return random_action(obs.holding, env.primitives, obs.depth_hm.shape, rng, clear)

    def run(self, spec: RunSpec) -> RunLog:
        """Play one run to its end; an exception becomes a run that ended with "error: …"."""
        start = time.perf_counter()
        try:
            return self._run(spec, start)
        except Exception as err:  # one broken run must not end a 330-run evaluation
            log.exception("run %s seed %d failed", spec.case, spec.seed)
            return RunLog(spec.case, spec.seed, 0, f"error: {type(err).__name__}: {err}", (),
                          time.perf_counter() - start)

    def _run(self, spec: RunSpec, start: float) -> RunLog:
        cfg = run_config(self.base, spec)
        env = self.env(cfg)
        trainer = self.trainer(cfg) if self.setup.learning else None
        if self.engine is not None:
            self.engine.load_state(self.weights)
        obs = env.reset(spec.seed)
        present = int(objects_in_workspace(env.scene))
        ideal = ideal_actions(spec.task, max(1, present), spec.goal_height)
        rng = np.random.default_rng(spec.seed)  # greedy: only ties would draw from it; random: every action
        steps: list[StepLog] = []
        end_reason = "step_limit"
        memory = FailureMemory.for_task(cfg)
        for step in range(spec.max_steps):
            action = self.act(env, obs, cfg, rng, memory)
            t0 = time.time_ns()
            result = env.step(action)
            memory.record(action, bool(result.success), result.progress_before, result.progress_after)
            steps.append(StepLog(action.primitive, bool(result.success), failure_cause(action, result)))
            if trainer is not None and self.engine is not None:
                msg = TransitionMsg.from_step(obs, action, result, actor_id="eval",
                                              episode_id=f"{spec.case}-{spec.seed}", step=step, start_ns=t0,
                                              end_ns=max(t0, time.time_ns()), task=spec.task)
                trainer.train_step([(msg, 1.0, 0)])
                self.engine.load_state(trainer.state_tensors())
            if result.done:
                end_reason = result.done_reason
                break
            obs = result.observation
        return RunLog(spec.case, spec.seed, ideal, end_reason, tuple(steps), time.perf_counter() - start)


def failure_cause(action: Action, result: StepResult) -> str:
    """Why a pick failed: the simulator's grasp cause (actor/sim/grasp_check.py), else the environment's
    reason ("unreachable", ...); "" for a success or another primitive."""
    if result.success or action.primitive != "pick":
        return ""
    grasp = result.info.get("grasp")
    return str(grasp) if grasp and grasp != "held" else (result.detail or "failed")


_WORKER: Worker | None = None


def init_worker(setup: EvalSetup) -> None:
    """Process-pool initializer: build this process's Worker."""
    global _WORKER
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it lets the runs under way finish
    logging.getLogger("romannet").setLevel(logging.WARNING)  # the parent reports progress
    _WORKER = Worker(setup)


def run_in_worker(spec: RunSpec) -> RunLog:
    """Process-pool task: one run on this process's Worker."""
    if _WORKER is None:
        raise RuntimeError("init_worker() was not called in this process")
    return _WORKER.run(spec)
