"""The learner's training step: RoManNet, an optional target net, SGD, the LAE rate (no threads, no transport).

One `train_step(batch)`:
1. V(s_{t+1}) by an explicit no-grad forward pass over the nets allowed in s_{t+1} (the target net's when
   enabled, else the online net's), only for items that bootstrap (R_tp > 0 and not done: eta = 0 or the
   episode's end make V irrelevant, so its forward pass is skipped).
2. Labels (learner.targets.q_label): R_tpg + eta*gamma*V on the TPG support; Y at the executed pixel. Each
   item trains on a window around its executed pixel (learner/crop.py), turned by a multiple of pi / 16
   and mirrored or not with learner.augment = "rotate" (learner/augment.py).
3. Items grouped by executed primitive, each group one batched forward pass of that primitive's net, its last
   conv and heads on the region each item's loss reads (learner.head_crop; learner/crop.py) (a pick
   net with a Q per closing angle, model.pick_angle_bins: each item's executed angle's map); the loss
   (learner/losses.py, whose docstring has the formulas): the Huber loss over each label's support
   + the rotation loss on successes (at the executed pixel, or over the support with learner.rotation_support
   = "kernel") + learner.executed_pixel_weight x the paper's Huber(Q(s_t, a_t) - Y_t) at the executed pixel,
   times the item's importance-sampling weight, averaged over the batch. Only the executed
   primitives' nets get gradients; the others keep `.grad is None`, so SGD skips them entirely (no weight
   decay, no momentum).
4. One SGD step at learner.lr, halved every learner.lr_halve_every_updates (learner/schedule.py); the
   exploration rate is updated with the paper's L_t (the Huber of the executed pixel's TD error, averaged
   over the batch).

BatchNorm: the nets train in train mode (batch statistics). Even at batch 1 a conv BN layer normalises
over h*w >= 16*16 positions per channel, so per-image statistics are well defined; VPG trains the same way.
Value estimates that leave the step (V(s_{t+1}), and the actors' decisions) use eval mode, i.e. the
running statistics the published weights carry, so the bootstrap sees the same function the actors act on.

CPU numerics (LearnerConfig): channels_last memory format and bf16 autocast (fp32 master weights, fp32
loss and optimiser). See docs/benchmarks.md and bench/learner.py for what each buys.
"""

from __future__ import annotations

import copy
import logging
import time
import types
from collections import defaultdict
from collections.abc import Iterable, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from romannet.common.config import ExplorationConfig, ModelConfig, RewardConfig, TaskConfig
from romannet.common.config_learner import LearnerConfig
from romannet.common.errors import ConfigError
from romannet.common.exploration import ExplorationRate
from romannet.common.grasp_clearance import angle_bin
from romannet.common.model import RoManNet, preprocess_batch, state_dict_to_tensors
from romannet.common.policy import nets_to_run, resolve_precision
from romannet.common.wire_messages import PriorityUpdateMsg, SampleBatchMsg, TransitionMsg

from .augment import moved_window, symmetry_index, window_size
from .crop import crop_origin, head_region
from .losses import (
    executed_pixel_loss,
    item_loss,
    q_loss,
    rotation_kernel_loss,
    rotation_pixel_loss,
    weighted_sum,
)
from .schedule import lr_at
from .targets import bootstrap_value, clip_value, q_label, return_range, rotation_targets, td_target

logger = logging.getLogger(__name__)

BatchItem = tuple[TransitionMsg, float, int]  # (transition, importance-sampling weight, replay item id)


@dataclass(frozen=True)
class StepStats:
    """What one update did. Losses are dimensionless (Q is in reward units); per-item tuples follow the
    batch order."""

    loss: float  # the optimised objective: mean over items of is_weight * (Q loss + w_rot * rotation loss)
    loss_by_primitive: dict[str, float]  # mean unweighted item loss per executed primitive
    td_errors: tuple[float, ...]  # |Q(s_t, a_t) - Y| at the executed pixel (new replay priorities)
    targets: tuple[float, ...]  # Y per item
    item_ids: tuple[int, ...]
    q_mean: dict[str, float]  # over the Q maps the step computed in that net (with head_crop: the loss regions)
    q_max: dict[str, float]
    exploration_loss: float  # the paper's L_t: mean over items of Huber(TD error at the executed pixel)
    exploration_rate: float  # after this step's update
    updates: int  # updates done, this one included
    duration_s: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)

    def priority_update(self) -> PriorityUpdateMsg:
        """The replay priorities of this batch: |TD error| per item id."""
        return PriorityUpdateMsg(self.item_ids, self.td_errors)


class _GroupInputs(NamedTuple):
    """One primitive's items in their training windows: labels and supports (k, h, w), input x, executed
    pixels rows, cols (k,) and angles (radians), after the window's symmetry where learner.augment is on."""

    label: Tensor
    support: Tensor
    x: Tensor
    rows: Tensor
    cols: Tensor
    angles: list[float]


class _GroupLoss(NamedTuple):
    """One primitive's share of a step: its IS-weighted summed loss (differentiable) and per-item values."""

    objective: Tensor
    item_losses: list[float]  # L per item, unweighted
    td_errors: list[float]  # |Q(s_t, a_t) - Y|
    pixel_losses: list[float]  # the paper's L_t = Huber(Q(s_t, a_t) - Y)
    q_mean: float
    q_max: float


def _fp32_head_forward(self: torch.nn.Conv2d, x: Tensor) -> Tensor:
    # bf16 keeps 8 mantissa bits: a Q map rounded to them moves TD errors and argmaxes by ~0.4 %, so the
    # 1x1 heads (a negligible share of the FLOPs) run in fp32 on the bf16 features, as the actors' do.
    with torch.autocast(x.device.type, enabled=False):
        return torch.nn.functional.conv2d(x.float(), self.weight, self.bias)


def _fp32_heads(model: RoManNet) -> None:
    """Make every net's Q and rotation heads compute in fp32 under autocast (state_dict keys unchanged)."""
    for net in model.nets.values():
        for head in (net.q_head, net.rot_head):
            head.forward = types.MethodType(_fp32_head_forward, head)


def _head_crop(g: _GroupInputs, features: Tensor, margin: int) -> tuple[_GroupInputs, Tensor]:
    """Each item's labels, support, executed pixel and last features cut to the region its loss reads
    (learner/crop.py, head_region): the 9x9 conv and the heads then run on that region only, with the same
    losses and gradients as on the whole window."""
    boxes = []
    for k in range(len(g.support)):
        rows = torch.nonzero(g.support[k].any(dim=1)).flatten().tolist() + [int(g.rows[k])]
        cols = torch.nonzero(g.support[k].any(dim=0)).flatten().tolist() + [int(g.cols[k])]
        boxes.append((min(rows), max(rows), min(cols), max(cols)))
    (rh, rw), origins = head_region(boxes, tuple(g.support.shape[-2:]), margin)

    def cut(t: Tensor) -> Tensor:
        return torch.stack([t[k, ..., r0:r0 + rh, c0:c0 + rw] for k, (r0, c0) in enumerate(origins)])

    r0s = torch.tensor([r0 for r0, _ in origins], device=g.rows.device)
    c0s = torch.tensor([c0 for _, c0 in origins], device=g.cols.device)
    return g._replace(label=cut(g.label), support=cut(g.support), rows=g.rows - r0s, cols=g.cols - c0s), \
        cut(features)


def value_fresh(value_version: int | None, version: int, max_age: int) -> bool:
    """Whether a V(s_{t+1}) computed with weights `value_version` still stands in for a forward pass at the
    learner's weights `version` (update count + version offset): at most max_age versions older (0: never).
    A bootstrap from weights a little behind the online net is what a target network does; an older one is
    recomputed, so replayed items do not keep the stale targets they were inserted with."""
    return max_age > 0 and value_version is not None and 0 <= version - value_version <= max_age


def actor_value_usable(t: TransitionMsg, version: int, max_age: int) -> bool:
    """Whether the actor's V(s_{t+1}) (its next decision's, on exactly the function it acts on) was sent and
    is fresh (`value_fresh`)."""
    return t.next_value is not None and value_fresh(t.next_value_version, version, max_age)


ValueKey = tuple[str, str, int]


def value_key(t: TransitionMsg) -> ValueKey:
    """A transition's identity, as the replay server deduplicates it."""
    return t.actor_id, t.episode_id, t.step


def batch_items(batch: SampleBatchMsg) -> list[BatchItem]:
    """(transition, is_weight, item_id) triples of a decoded sample batch."""
    items = []
    for it in batch.items:
        if not isinstance(it.transition, TransitionMsg):
            raise TypeError(f"item {it.item_id} holds encoded bytes; decode the batch first")
        items.append((it.transition, it.is_weight, it.item_id))
    return items


class Trainer:
    """RoManNet + optional target net + SGD + exploration rate, stepping on lists of replay items."""

    def __init__(self, model_cfg: ModelConfig, learner_cfg: LearnerConfig, reward_cfg: RewardConfig,
                 task_cfg: TaskConfig, seed: int | None = None,
                 exploration_cfg: ExplorationConfig | None = None, device: str | None = None):
        self.model_cfg, self.cfg, self.reward_cfg, self.task_cfg = model_cfg, learner_cfg, reward_cfg, task_cfg
        self.exploration_cfg = exploration_cfg or ExplorationConfig()
        self.seed = learner_cfg.seed if seed is None else seed
        device = device or learner_cfg.device  # an explicit argument (the benchmark's) wins over the config
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise ConfigError("learner.device", device, "CUDA is not available on this machine; use 'cpu'")
        self.device = torch.device(device)
        self.precision = ("bf16" if learner_cfg.precision == "auto" else learner_cfg.precision) \
            if self.device.type == "cuda" else resolve_precision(learner_cfg.precision)
        if learner_cfg.num_threads > 0:
            torch.set_num_threads(learner_cfg.num_threads)
        self.memory_format = torch.channels_last if learner_cfg.channels_last else torch.contiguous_format
        self.model = RoManNet(model_cfg, seed=self.seed).to(self.device, memory_format=self.memory_format)
        self.model.train()
        _fp32_heads(self.model)
        self.target: RoManNet | None = None
        if learner_cfg.target_network:
            self.target = copy.deepcopy(self.model).eval().requires_grad_(False)
        self.optimizer = torch.optim.SGD(self.model.parameters(), lr=learner_cfg.lr,
                                         momentum=learner_cfg.momentum, weight_decay=learner_cfg.weight_decay)
        self.exploration = ExplorationRate(self.exploration_cfg)
        self.updates = 0
        self.version_offset = 0  # weights version minus update count (learner/versions.py; 0 until a crash)
        self.primitives = task_cfg.primitives
        self.actor_values_used = 0  # V(s_{t+1}) taken from the actor's next decision
        self.values_computed = 0  # V(s_{t+1}) computed here by a forward pass
        self.values_reused = 0  # V(s_{t+1}) computed here earlier and still fresh (`value_fresh`)
        # What this learner computed, by transition: (weights version, V before clipping). The rule that lets
        # an actor's value stand in for a forward pass lets an earlier pass's stand in too (a prioritised
        # item comes back within a few updates); entries older than the rule allows are dropped.
        self._values: dict[ValueKey, tuple[int, float]] = {}
        self._values_pruned_at = 0

    # ------------------------------------------------------------------------------------------ helpers
    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return nullcontext()

    def _inputs(self, colors: Sequence[np.ndarray], depths: Sequence[np.ndarray]) -> Tensor:
        x = preprocess_batch(np.stack(colors), np.stack(depths))
        return x.to(self.device).contiguous(memory_format=self.memory_format)

    def state_tensors(self) -> dict[str, Tensor]:
        """The online net's weights and BN statistics as a flat CPU tensor dict (what actors load)."""
        return state_dict_to_tensors(self.model)

    def sync_target(self) -> None:
        """Copy the online net into the target net (no-op without a target net)."""
        if self.target is not None:
            self.target.load_state_dict(self.model.state_dict())

    @torch.no_grad()
    def next_state_values(self, transitions: Sequence[TransitionMsg]) -> list[float]:
        """V(s_{t+1}) per transition, 0 where it cannot matter (done, or R_tp <= 0 so eta = 0)."""
        values = [0.0] * len(transitions)
        need = [i for i, t in enumerate(transitions) if not t.done and t.reward > 0]
        bounds = return_range(self.reward_cfg, self.cfg.gamma) if self.cfg.bootstrap_clip else None
        version = self.updates + self.version_offset  # what the actors' next_value_version counts in
        from_actor = [i for i in need if actor_value_usable(transitions[i], version, self.cfg.actor_value_max_age)]
        for i in from_actor:
            v = float(transitions[i].next_value)
            values[i] = clip_value(v, bounds) if bounds is not None else v
        self.actor_values_used += len(from_actor)
        taken = set(from_actor)
        need = [i for i in need if i not in taken]
        max_age = self.cfg.actor_value_max_age
        if version - self._values_pruned_at > max_age:
            self._values = {k: e for k, e in self._values.items() if value_fresh(e[0], version, max_age)}
            self._values_pruned_at = version
        own = {i: self._values.get(value_key(transitions[i])) for i in need}
        reused = {i: e[1] for i, e in own.items() if e is not None and value_fresh(e[0], version, max_age)}
        for i, v in reused.items():
            values[i] = clip_value(v, bounds) if bounds is not None else v
        self.values_reused += len(reused)
        need = [i for i in need if i not in reused]
        self.values_computed += len(need)
        if not need:
            return values
        net_model = self.target if self.target is not None else self.model
        was_training = net_model.training
        net_model.eval()  # the running statistics: the same function the actors act on
        try:
            by_net: dict[str, list[int]] = defaultdict(list)
            for i in need:
                for p in nets_to_run(transitions[i].holding_after, self.primitives):
                    by_net[p].append(i)
            maxima: dict[int, dict[str, float]] = defaultdict(dict)
            for p, idx in by_net.items():
                x = self._inputs([transitions[i].color_after for i in idx], [transitions[i].depth_after for i in idx])
                with self._autocast():
                    q, _ = net_model.nets[p](x)
                best = q.float().flatten(1).amax(dim=1).tolist()  # over the angles too (a Q per angle)
                for i, m in zip(idx, best, strict=True):
                    maxima[i][p] = m
            for i in need:
                t = transitions[i]
                values[i] = bootstrap_value(maxima[i], t.holding_after, self.primitives, t.done)
                if max_age > 0:
                    self._values[value_key(t)] = (version, values[i])
                if bounds is not None:
                    values[i] = clip_value(values[i], bounds)
        finally:
            net_model.train(was_training)
        return values

    # ------------------------------------------------------------------------------------------ the step
    def train_step(self, batch: Iterable[BatchItem]) -> StepStats:
        """One SGD update on (transition, is_weight, item_id) items; see the module docstring."""
        start = time.perf_counter()
        items = list(batch)
        if not items:
            raise ValueError("train_step needs at least one item")
        transitions = [t for t, _, _ in items]
        for _, w, _ in items:
            if not (w > 0 and np.isfinite(w)):
                raise ValueError(f"importance-sampling weight {w!r} must be finite and > 0")
        cfg, n = self.cfg, len(items)
        v_next = self.next_state_values(transitions)
        targets = [td_target(t.reward, v, cfg.gamma) for t, v in zip(transitions, v_next, strict=True)]

        groups: dict[str, list[int]] = defaultdict(list)
        for i, t in enumerate(transitions):
            groups[t.action.primitive].append(i)

        self.optimizer.zero_grad(set_to_none=True)
        total = torch.zeros((), device=self.device)
        td_errors = [0.0] * n
        pixel_losses = [0.0] * n
        loss_by_primitive: dict[str, float] = {}
        q_mean: dict[str, float] = {}
        q_max: dict[str, float] = {}
        for p, idx in groups.items():
            g = self._group_loss(p, [transitions[i] for i in idx], [v_next[i] for i in idx],
                                 [targets[i] for i in idx], [items[i][1] for i in idx], [items[i][2] for i in idx])
            total = total + g.objective
            loss_by_primitive[p] = float(np.mean(g.item_losses))
            q_mean[p], q_max[p] = g.q_mean, g.q_max
            for k, i in enumerate(idx):
                td_errors[i], pixel_losses[i] = g.td_errors[k], g.pixel_losses[k]
        loss = total / n
        if not torch.isfinite(loss):  # a diverged learner must not step (nor publish, nor move the LAE rate)
            raise FloatingPointError(f"training loss is {float(loss.detach())} at update {self.updates + 1}; "
                                     "lower learner.lr or check the batch")
        loss.backward()
        if cfg.max_grad_norm > 0:  # rescales the whole gradient when its L2 norm is larger (not per tensor)
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.max_grad_norm)
        lr = lr_at(cfg.lr, self.updates, cfg.lr_halve_every_updates)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        self.optimizer.step()
        self.updates += 1
        if self.target is not None and self.updates % cfg.target_sync_every_updates == 0:
            self.sync_target()
        exploration_loss = float(np.mean(pixel_losses))
        rate = self.exploration.update(exploration_loss)
        return StepStats(loss=float(loss.detach()), loss_by_primitive=loss_by_primitive, td_errors=tuple(td_errors),
                         targets=tuple(targets), item_ids=tuple(int(i) for _, _, i in items), q_mean=q_mean,
                         q_max=q_max, exploration_loss=exploration_loss, exploration_rate=rate,
                         updates=self.updates, duration_s=time.perf_counter() - start)

    def _group_inputs(self, ts: Sequence[TransitionMsg], v_next: Sequence[float],
                      item_ids: Sequence[int]) -> _GroupInputs:
        """The nets' input, Q labels and executed pixels of one primitive's items, each in its training window
        (learner.train_crop_px; the whole heightmap with 0 or a window as large as the image); with
        learner.augment = "rotate" the window is centred on the executed pixel, turned and mirrored by the
        item's symmetry (learner/augment.py)."""
        cfg = self.cfg
        h, w = ts[0].shape
        crop = cfg.train_crop_px if 0 < cfg.train_crop_px < min(h, w) else 0
        labels, supports, colors, depths, rows, cols, angles = [], [], [], [], [], [], []
        for t, v, item_id in zip(ts, v_next, item_ids, strict=True):
            a = t.action
            lab, sup = q_label((h, w), a.row, a.col, a.angle_rad, t.reward, v, cfg.gamma, self.reward_cfg)
            if cfg.augment == "rotate":
                k, mirrored = symmetry_index(item_id, self.updates)
                images, row, col, angle = moved_window(lab, sup, t.color_before, t.depth_before, a.row, a.col,
                                                       a.angle_rad, k, mirrored, window_size((h, w), crop))
            else:
                r0, c0 = crop_origin((h, w), a.row, a.col, crop) if crop else (0, 0)
                win = (slice(r0, r0 + crop), slice(c0, c0 + crop)) if crop else (slice(None), slice(None))
                images = [lab[win], sup[win], t.color_before[win], t.depth_before[win]]
                row, col, angle = a.row - r0, a.col - c0, a.angle_rad
            for out, im in zip((labels, supports, colors, depths), images, strict=True):
                out.append(im)
            rows.append(row)
            cols.append(col)
            angles.append(angle)
        return _GroupInputs(torch.from_numpy(np.stack(labels)).to(self.device),
                            torch.from_numpy(np.stack(supports)).to(self.device), self._inputs(colors, depths),
                            torch.tensor(rows, device=self.device), torch.tensor(cols, device=self.device), angles)

    def _group_loss(self, p: str, ts: list[TransitionMsg], v_next: list[float], targets: list[float],
                    is_weights: list[float], item_ids: list[int]) -> _GroupLoss:
        """The loss of one primitive's items in one forward pass of its net (learner/losses.py)."""
        cfg = self.cfg
        g = self._group_inputs(ts, v_next, item_ids)
        net = self.model.nets[p]
        with self._autocast():
            features = net.features(g.x)
            if cfg.head_crop:
                g, features = _head_crop(g, features, net.head_radius())
                features = features.contiguous(memory_format=self.memory_format)
            q, rot = net.head(features)
        q, rot = q.float(), rot.float()
        ar = torch.arange(len(ts), device=self.device)
        if q.dim() == 4:  # a Q per closing angle: each item's label trains its executed angle's map
            bins = angle_bin(np.array(g.angles), q.shape[1])
            q = q[ar, torch.from_numpy(bins).to(self.device)]
        q_exec = q[ar, g.rows, g.cols]
        y = torch.tensor(targets, device=self.device)
        is_w = torch.tensor(is_weights, device=self.device, dtype=torch.float32)
        q_losses = q_loss(q, g.label, g.support, cfg.huber_delta, cfg.loss_reduction)
        rho, rho_w = rotation_targets(g.angles, [t.success for t in ts], p,
                                      self.model.cfg.rotation_harmonics)
        rho, rho_w = rho.to(self.device), rho_w.to(self.device)
        rot_losses = (rotation_kernel_loss(rot, rho, rho_w, g.support) if cfg.rotation_support == "kernel"
                      else rotation_pixel_loss(rot[ar, :, g.rows, g.cols], rho, rho_w))
        pixel_losses = executed_pixel_loss(q_exec, y, cfg.huber_delta)
        item_losses = item_loss(q_losses, rot_losses, cfg.rotation_loss_weight, pixel_losses,
                                cfg.executed_pixel_weight)
        return _GroupLoss(weighted_sum(is_w, item_losses), item_losses.detach().tolist(),
                          [abs(e) for e in (q_exec - y).detach().tolist()], pixel_losses.detach().tolist(),
                          float(q.detach().mean()), float(q.detach().max()))
