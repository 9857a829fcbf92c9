"""The learner service: Algorithm 1's loop around the Trainer, wired to the replay, the actors and the disk.

    with open_session(zenoh_config) as session:
        client = TolerantReplayClient(session, cfg.run_id, expected_shape)
        run_learner(cfg, "runs/run-1", client, session, stop_event, resume=False)

Each turn of the loop: wait until the replay holds learner.min_replay_size transitions and the replay-ratio
cap allows another update (learner/gate.py); sample a batch (a rate-limited or unanswered sample is waited
out and retried); train one step; send |TD error| per item id back as priorities; publish the exploration
rate; every publish_every_updates publish the weights; every checkpoint_every_updates write a checkpoint.
A version is the update count plus an offset that is 0 unless the learner repeats updates it already
published (a crash, then a resume from an older checkpoint): versions.py keeps them unique across processes.
A resume takes the newest intact checkpoint; with none intact it starts fresh, saying so in one line.

Stopping: stop_event (set by the SIGTERM/SIGINT handler in learner/main.py) is checked between steps, so
the step under way finishes; then the latest weights are published, a checkpoint is written, and the
publisher, liveliness token and metrics are closed. The caller closes the session.

Corrupt data never stops training: items that fail to decode are skipped, counted, and given priority 0
(TolerantReplayClient); a whole batch that fails to decode is skipped and counted.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import zenoh

from romannet.common.config import Config
from romannet.common.config_pacing import transitions_before_first_update
from romannet.common.configbase import write_toml
from romannet.common.errors import DecodeError
from romannet.common.interfaces import ReplayClient
from romannet.common.keys import RunKeys
from romannet.common.model import preprocess
from romannet.common.weights_wire import resolve_wire_dtype
from romannet.common.wire_messages import PriorityUpdateMsg, SampleBatchMsg, TransitionMsg
from romannet.common.zenoh_session import ZenohQueryError

from .checkpoint import load_checkpoint, save_checkpoint, start_from_weights
from .ckpt_integrity import NoIntactCheckpoint
from .gate import ReplayGate
from .metrics import LearnerMetrics
from .publisher import WeightsPublisher
from .trainer import StepStats, Trainer, batch_items
from .versions import VersionClock

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ServiceOptions:
    """Timing of the service itself (training hyper-parameters and cadences are in LearnerConfig).

    sample_timeout_s: deadline of one sample request, seconds (also bounds how long a stop waits);
    stats_every_s: how often replay stats are read for the min-size and ratio checks; idle_wait_s: pause
    while waiting for data; image_every_updates: action images to TensorBoard (0 = never);
    plot_every_s: learning-curve PNG redraws; log_every_s: progress log lines; max_updates: stop once the
    update count reaches it, like a stop signal (0 = no limit; offline training runs to a set length).
    """

    sample_timeout_s: float = 2.0
    stats_every_s: float = 1.0
    idle_wait_s: float = 0.1
    image_every_updates: int = 100
    plot_every_s: float = 60.0
    log_every_s: float = 30.0
    max_updates: int = 0


class _Counters:
    """Run totals for logs and the returned summary."""

    def __init__(self) -> None:
        self.steps = 0
        self.skipped_items = 0
        self.skipped_batches = 0
        self.sample_timeouts = 0
        self.waited_s = 0.0
        self.checkpointed_at: int | None = None  # update count of the newest checkpoint on disk


def run_learner(cfg: Config, run_dir: str | Path, replay_client: ReplayClient, session: zenoh.Session,
                stop_event: threading.Event, resume: bool = False, options: ServiceOptions | None = None,
                ready: Callable[[Trainer], None] | None = None,
                init_weights: Mapping[str, torch.Tensor] | None = None) -> dict[str, Any]:
    """Train until stop_event is set; returns a summary (updates, skipped items, ...).

    cfg: the root config (its learner, model, reward, task, exploration sections and run_id).
    resume: continue from the newest intact checkpoint in run_dir (a fresh start, logged, if none is intact).
    init_weights: a new run's starting weights (checkpoint.read_init_weights), published as version 0.
    ready(trainer): called once weights are published and the liveliness token is up.
    """
    opts = options or ServiceOptions()
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    lcfg = cfg.learner
    trainer = Trainer(cfg.model, lcfg, cfg.reward, cfg.task, exploration_cfg=cfg.exploration, device=lcfg.device)
    saved_offset, resumed_from = _start_state(trainer, run_dir, resume, init_weights)
    clock = VersionClock.start(run_dir, trainer.updates, saved_offset, resumed_from, lcfg.publish_every_updates)
    trainer.version_offset = clock.offset
    write_toml(cfg, run_dir / "config.toml")  # the resolved config of this run, next to its results
    keys = RunKeys(cfg.run_id)
    counters = _Counters()
    if resumed_from is not None:
        counters.checkpointed_at = trainer.updates
    metrics = LearnerMetrics(run_dir, opts.image_every_updates, opts.plot_every_s,
                             first_update=transitions_before_first_update(cfg.replay, lcfg))
    wire_dtype = resolve_wire_dtype(lcfg.weights_wire_dtype, cfg.model.precision)
    publisher = WeightsPublisher(session, cfg.run_id, wire_dtype)
    log.info("weights go out in %s (learner.weights_wire_dtype = %s)", wire_dtype, lcfg.weights_wire_dtype)
    token = None
    try:
        # Weights first, then the token: an actor that reacts to the token fetches and finds them.
        publisher.publish_weights(clock.claim(trainer.updates), trainer.state_tensors())
        publisher.publish_exploration(clock.claim(trainer.updates), trainer.exploration.value,
                                      trainer.exploration_cfg.policy)
        token = session.liveliness().declare_token(keys.learner_alive)
        if ready is not None:
            ready(trainer)
        _loop(trainer, replay_client, publisher, clock, metrics, stop_event, counters, opts)
    finally:
        log.info("learner stopping at update %d: final weights and checkpoint", trainer.updates)
        try:
            if publisher.version != clock.version(trainer.updates):
                publisher.publish_weights(clock.claim(trainer.updates), trainer.state_tensors())
        except Exception as exc:  # non-finite weights or a closed session: the checkpoint matters more
            log.warning("could not publish the final weights: %s", exc)
        if counters.checkpointed_at != trainer.updates:  # else the periodic one at this update is it
            save_checkpoint(trainer, run_dir, clock.offset)
        clock.release(trainer.updates, f"ckpt-{trainer.updates:09d}")
        if token is not None:
            token.undeclare()
        publisher.close()
        metrics.close()
    summary = {"updates": trainer.updates, "steps_this_run": counters.steps,
               "skipped_items": counters.skipped_items, "skipped_batches": counters.skipped_batches,
               "sample_timeouts": counters.sample_timeouts, "waited_s": round(counters.waited_s, 3),
               "weights_version": publisher.version, "weights_served": publisher.served}
    log.info("learner stopped: %s", summary)
    return summary


def _start_state(trainer: Trainer, run_dir: Path, resume: bool,
                 init_weights: Mapping[str, torch.Tensor] | None) -> tuple[int, str | None]:
    """Load the newest intact checkpoint (resume) or the init weights into the trainer; returns the loaded
    checkpoint's version offset and name, (0, None) for a fresh start."""
    if resume:
        try:
            ckpt = load_checkpoint(trainer, run_dir)  # logs it, and each newer damaged one it skipped
            return int(ckpt.state.get("version_offset", 0)), ckpt.path.name
        except NoIntactCheckpoint as err:
            log.warning("%s: starting fresh at update 0", err)
    if init_weights is not None:
        start_from_weights(trainer, init_weights)
    return 0, None


def _loop(trainer: Trainer, client: ReplayClient, publisher: WeightsPublisher, clock: VersionClock,
          metrics: LearnerMetrics, stop: threading.Event, counters: _Counters, opts: ServiceOptions) -> None:
    lcfg = trainer.cfg
    gate = ReplayGate(client, lcfg.min_replay_size, lcfg.max_updates_per_insert, opts.stats_every_s,
                      stats_timeout_s=opts.sample_timeout_s)
    gate.start(trainer.updates)
    step_times: deque[float] = deque(maxlen=20)  # monotonic end times of recent steps, for updates/s
    next_log_s = time.monotonic() + opts.log_every_s
    while not stop.is_set():
        if 0 < opts.max_updates <= trainer.updates:
            log.info("reached %d updates (max_updates): stopping", trainer.updates)
            break
        if not gate.ready(trainer.updates):
            t0 = time.monotonic()
            stop.wait(opts.idle_wait_s)
            counters.waited_s += time.monotonic() - t0
            next_log_s = _maybe_log(next_log_s, opts, "learner waiting: %s", gate.waiting_reason)
            continue
        t0 = time.monotonic()
        batch = _sample(client, lcfg.batch_size, opts, counters)
        sample_latency_s = time.monotonic() - t0
        if batch is None or not batch.items:
            stop.wait(opts.idle_wait_s)
            continue
        items = batch_items(batch)
        try:
            stats = trainer.train_step(items)
        except DecodeError as err:  # defensive: a transition the trainer could not turn into tensors
            counters.skipped_batches += 1
            log.warning("skipped a batch the trainer could not use: %s", err)
            continue
        counters.steps += 1
        client.update_priorities(stats.priority_update())
        publisher.publish_exploration(clock.claim(stats.updates), stats.exploration_rate,
                                      trainer.exploration_cfg.policy)
        if stats.updates % lcfg.publish_every_updates == 0:
            publisher.publish_weights(clock.claim(stats.updates), trainer.state_tensors())
        step_times.append(time.monotonic())
        _record(trainer, metrics, stats, [t for t, _, _ in items], batch.buffer_size, gate, step_times,
                sample_latency_s, counters, publisher)
        if stats.updates % lcfg.checkpoint_every_updates == 0:
            save_checkpoint(trainer, metrics.run_dir, clock.offset)
            counters.checkpointed_at = stats.updates
            metrics.flush()
        next_log_s = _maybe_log(next_log_s, opts, "update %d: loss %.4g, explore %.3f, replay %d, V(s') from "
                                "the actors %d, computed %d, reused %d", stats.updates, stats.loss, stats.exploration_rate,
                                batch.buffer_size, trainer.actor_values_used, trainer.values_computed,
                                trainer.values_reused)


def _sample(client: ReplayClient, batch_size: int, opts: ServiceOptions,
            counters: _Counters) -> SampleBatchMsg | None:
    """One batch, or None when the replay held it back, did not answer, or sent only garbage."""
    try:
        batch = client.sample(batch_size, timeout_s=opts.sample_timeout_s)
    except TimeoutError as err:  # RateLimitedError or NoReplyError: wait and retry
        counters.sample_timeouts += 1
        log.debug("sample: %s", err)
        return None
    except ZenohQueryError as err:  # an error reply ("overloaded", "shutting_down"): wait and retry
        counters.sample_timeouts += 1
        log.warning("sample refused by the replay server: %s", err)
        return None
    except DecodeError as err:  # a plain ReplayClient refuses the whole batch for one bad item
        counters.skipped_batches += 1
        log.warning("skipped an undecodable batch (%d so far): %s", counters.skipped_batches, str(err)[:300])
        return None
    corrupt = getattr(client, "last_corrupt", ())  # TolerantReplayClient lists the items it dropped
    if corrupt:
        counters.skipped_items += len(corrupt)
        log.warning("skipped %d corrupt item(s) (%d so far), e.g. %s", len(corrupt), counters.skipped_items,
                    corrupt[0].reason)
        ids = tuple(c.item_id for c in corrupt if c.item_id is not None)
        if ids:  # priority 0: the buffer stops offering them (rank-based sampling: the lowest rank)
            client.update_priorities(PriorityUpdateMsg(ids, (0.0,) * len(ids)))
    return batch


def _record(trainer: Trainer, metrics: LearnerMetrics, stats: StepStats, transitions: list[TransitionMsg],
            replay_size: int, gate: ReplayGate, step_times: deque[float], sample_latency_s: float,
            counters: _Counters, publisher: WeightsPublisher) -> None:
    """Scalars for this update, and an action image when one is due."""
    span_s = step_times[-1] - step_times[0] if len(step_times) > 1 else 0.0
    # Policy lag: how many updates behind the current weights the sampled actions were chosen.
    lag = (publisher.version or 0) - float(np.mean([t.policy_version for t in transitions]))
    values: dict[str, float | int | None] = {
        "loss": stats.loss, "td_error_mean": float(np.mean(stats.td_errors)),
        "td_error_max": float(np.max(stats.td_errors)), "explore_rate": stats.exploration_rate,
        "updates_per_s": (len(step_times) - 1) / span_s if span_s > 0 else None,
        "sample_latency_s": sample_latency_s, "step_time_s": stats.duration_s,
        "replay_size": replay_size, "replay_inserts": gate.state.inserts, "policy_lag": lag,
        "weights_version": publisher.version, "batch_items": len(transitions),
        "skipped_items": counters.skipped_items,
    }
    for p, v in stats.loss_by_primitive.items():
        values[f"loss_{p}"] = v
    for p, v in stats.q_mean.items():
        values[f"q_mean_{p}"] = v
    for p, v in stats.q_max.items():
        values[f"q_max_{p}"] = v
    metrics.log_scalars(stats.updates, values)
    if metrics.wants_image(stats.updates):
        t = transitions[0]
        q_map = _q_map(trainer, t.color_before, t.depth_before, t.action.primitive)
        metrics.log_action_image(stats.updates, t.action.primitive, t.color_before, q_map, t.action.row,
                                 t.action.col, t.action.angle_rad)


@torch.no_grad()
def _q_map(trainer: Trainer, color_hm: np.ndarray, depth_hm: np.ndarray, primitive: str) -> np.ndarray:
    """The executed net's Q map after this update, in eval mode: running statistics stay untouched, so
    drawing an image never changes what is trained (checkpoint/resume stays exact)."""
    net = trainer.model.nets[primitive]
    was_training = net.training
    net.eval()
    try:
        q, _ = net(preprocess(color_hm, depth_hm).to(trainer.device))
    finally:
        net.train(was_training)
    q = q[0] if q.dim() == 3 else q[0].amax(dim=0)  # a Q per closing angle: the best angle's
    return q.float().cpu().numpy()


def _maybe_log(next_log_s: float, opts: ServiceOptions, fmt: str, *args: object) -> float:
    """Log at INFO at most every log_every_s seconds; returns the next time a line is due."""
    now = time.monotonic()
    if now < next_log_s:
        return next_log_s
    log.info(fmt, *args)
    return now + opts.log_every_s
