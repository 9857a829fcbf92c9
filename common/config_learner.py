"""Configuration of the learner: the paper's optimiser and target, the loss, CPU numerics, cadences.

One frozen dataclass, validated on construction: a bad value raises ConfigError naming the field, the value
and the fix. The root Config holds it as the `learner` section.

Batch size: the paper trains one sampled transition per step. On a CPU a step's cost is dominated by the
convolutions, whose per-image cost falls when several images of the same net go through one call (oneDNN
keeps the cores busy and amortises per-layer overhead). The default of 4 is the size where, on the
2-core development box, transitions trained per second were close to the plateau (see
docs/benchmarks.md, `romannet bench learner`) while each update still comes every ~second of work, so
the LAE rate and the published weights stay fresh. Set 1 for the paper's literal schedule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from .configbase import require


@dataclass(frozen=True)
class LearnerConfig:
    """RoManNet training (paper, "Learning the Action-Value Functions") and the learner's cadences."""

    # Optimiser: SGD as in the paper (the paper's "2^-5" weight decay is 2e-5 in the authors' code).
    lr: float = 1e-4
    # Halve the learning rate every this many updates (arc-l/vft halves it every 2,000 steps), so the late
    # updates move the greedy argmax less and a frozen checkpoint is the policy training converged to.
    # 0 = a constant rate (the paper's).
    lr_halve_every_updates: int = 0
    momentum: float = 0.9
    weight_decay: float = 2e-5
    # Target Y = R_tp + eta * gamma * V(s_{t+1}), eta = 1 iff R_tp > 0.
    gamma: float = 0.5
    batch_size: int = 4  # transitions per update (see the module docstring)
    huber_delta: float = 1.0  # the paper's Huber loss switches from quadratic to linear at |delta| = 1
    # "sum": per-pixel Huber losses summed over the label's support (every labelled pixel weighs what VPG's
    # single labelled pixel weighs); "mean": averaged over the support (the loss no longer grows with the
    # Gaussian's size). The paper does not say; the authors' code sums.
    loss_reduction: Literal["sum", "mean"] = "mean"
    # Extra weight on the executed pixel's own Huber(Q(s_t, a_t) - Y_t), the paper's L_t, added to the support
    # loss. With "mean" the executed pixel weighs 1/N of an N-pixel support, so a sharp peak of Q, which is
    # where the greedy argmax lands, is trained down only slowly (measured: a failed push's Q fell from 0.7
    # to 0.43-0.63 in 30 updates on those four items alone, docs/journal.md); 1 gives it the paper's weight.
    # 0 = the support loss alone.
    executed_pixel_weight: float = 1.0
    target_network: bool = False  # bootstrap V(s_{t+1}) from a lagged copy instead of the online net
    # Clip V(s_{t+1}) into the range a return can have, [0, largest reward weight / (1 - gamma)]: rewards are
    # >= 0 and <= that weight, so a V outside it is the nets' error. Off = the paper's target. Seen without it:
    # the place net's largest Q in a batch went from 7.6 to -0.4 in nine updates, and a successful pick's
    # target R + gamma V moves with it, from ~4 to below a failed pick's 0 (docs/journal.md).
    bootstrap_clip: bool = True
    target_sync_every_updates: int = 100  # copy online -> target every this many updates
    # Take V(s_{t+1}) from the actor's next decision (it runs the same nets on s_{t+1} to act), or from this
    # learner's own earlier pass on the same transition, when its weights are at most this many updates behind
    # the learner's, instead of a forward pass here; older values are recomputed (learner.trainer.value_fresh).
    # 0 = always compute here.
    actor_value_max_age: int = 100
    # Clip the gradient's global L2 norm to this before each step; 0 = off (the paper's and VPG's setting). A
    # summed loss over a Gaussian label's support makes early gradients large: clipping lets a higher lr train
    # without diverging.
    max_grad_norm: float = 0.0
    rotation_loss_weight: float = 1.0  # weight of the rotation head's squared error beside the Q loss
    # Where a success's angle trains the rotation head: "pixel" = the executed pixel only; "kernel" = every
    # pixel of the Q label's support (averaged), the executed angle being the target for the action poses
    # around it, as GR-ConvNet trains its angle maps over a grasp's region rather than one pixel.
    rotation_support: Literal["pixel", "kernel"] = "pixel"
    # Forward + backward over a window of this many pixels around each executed pixel instead of the whole
    # heightmap (learner/crop.py): 128 holds the label's support with the nets' receptive field around it, so
    # the losses equal the whole image's, at a third of the cost at 224 px. 0 = the whole heightmap.
    train_crop_px: int = 128
    # Run the last 9x9 conv and the heads only on the region the loss reads (the label's support and 4 px
    # around it) instead of the whole window: exactly the same losses and gradients (learner/crop.py,
    # head_region), with that conv, the step's largest, on a small share of the pixels. Off only to measure it.
    head_crop: bool = True
    # "rotate": train each item on a window centred on its executed pixel, turned by a multiple of pi / 16 and
    # mirrored or not, the action's angle moved with it (learner/augment.py), so a net with a Q per closing
    # angle learns every angle from every pick, as VPG's rotated inputs do; "none": as trained so far.
    augment: Literal["none", "rotate"] = "none"
    # CPU numerics. "bf16": autocast to bfloat16 for the convolutions (fp32 master weights and loss); it pays
    # only where the CPU computes bf16 natively (AMX / AVX512-BF16), elsewhere it is emulated and several
    # times slower than fp32. "auto": bf16 on such CPUs (and on CUDA), fp32 elsewhere.
    precision: Literal["auto", "fp32", "bf16"] = "auto"
    channels_last: bool = True
    num_threads: int = 0  # 0 = torch's default (one per core)
    device: str = "cpu"  # "cuda" / "cuda:N" trains on a GPU when the machine has one
    seed: int = 0
    # Cadences, in updates.
    # Every 100 updates, so a run can be evaluated while it trains: on a CPU that is a few minutes of updates,
    # and writing the default nets with their momentum (46 MB) takes ~0.3 s of it.
    checkpoint_every_updates: int = 100
    keep_checkpoints: int = 3  # older checkpoints are deleted after a new one is complete
    # New weights after every update: VPG acts on the net it has just trained, and an actor that keeps its
    # weights for many actions repeats the action that has just failed (docs/journal.md).
    publish_every_updates: int = 1
    # dtype of the published weights (common/weights_wire.py): "bf16" halves them and is exact for actors that
    # compute in bf16; "fp32" for a fleet with fp32 actors (CPUs without native bf16); "auto": bf16 when
    # model.precision resolves to bf16 on the learner's machine.
    weights_wire_dtype: Literal["auto", "fp32", "bf16"] = "auto"
    # Replay ratio: at most this many updates per newly inserted transition (the learner waits rather than
    # overfitting a small buffer); 0 = no cap.
    max_updates_per_insert: float = 4.0
    min_replay_size: int = 32  # transitions in the buffer before the first update

    def __post_init__(self) -> None:
        require(self.device == "cpu" or self.device == "cuda" or
                (self.device.startswith("cuda:") and self.device[5:].isdigit()), "learner.device", self.device,
                "must be 'cpu', 'cuda' or 'cuda:N'")
        require(math.isfinite(self.lr) and 0.0 < self.lr <= 1.0, "learner.lr", self.lr,
                "must be in (0, 1] (the paper uses 1e-4)")
        require(0 <= self.lr_halve_every_updates <= 10_000_000, "learner.lr_halve_every_updates",
                self.lr_halve_every_updates, "must be 0..10000000 updates (0 = a constant learning rate)")
        require(0.0 <= self.momentum < 1.0, "learner.momentum", self.momentum, "must be in [0, 1) (paper: 0.9)")
        require(0.0 <= self.weight_decay < 1.0, "learner.weight_decay", self.weight_decay,
                "must be in [0, 1) (paper: 2e-5)")
        require(0.0 <= self.gamma < 1.0, "learner.gamma", self.gamma, "must be in [0, 1) (paper: 0.5)")
        require(1 <= self.batch_size <= 256, "learner.batch_size", self.batch_size, "must be 1..256")
        require(math.isfinite(self.huber_delta) and self.huber_delta > 0, "learner.huber_delta",
                self.huber_delta, "must be a positive number (paper: 1)")
        require(math.isfinite(self.executed_pixel_weight) and 0.0 <= self.executed_pixel_weight <= 100.0,
                "learner.executed_pixel_weight", self.executed_pixel_weight,
                "must be in [0, 100] (0 = the support loss alone, 1 = the paper's weight on the executed pixel)")
        require(math.isfinite(self.max_grad_norm) and self.max_grad_norm >= 0, "learner.max_grad_norm",
                self.max_grad_norm, "must be a non-negative number (0 = no clipping)")
        require(0 <= self.actor_value_max_age <= 1_000_000, "learner.actor_value_max_age", self.actor_value_max_age,
                "must be 0..1000000 updates (0 = V(s_t+1) always computed by the learner)")
        require(self.target_sync_every_updates >= 1, "learner.target_sync_every_updates",
                self.target_sync_every_updates, "must be >= 1")
        require(0.0 <= self.rotation_loss_weight <= 100.0, "learner.rotation_loss_weight",
                self.rotation_loss_weight, "must be in [0, 100] (0 = the rotation head is not trained)")
        require(self.train_crop_px == 0 or (self.train_crop_px >= 32 and self.train_crop_px % 4 == 0),
                "learner.train_crop_px", self.train_crop_px,
                "must be 0 (the whole heightmap) or a multiple of 4 from 32 (the nets' stride; 128 holds their "
                "receptive field around the label)")
        require(self.augment in ("none", "rotate"), "learner.augment", self.augment,
                "must be 'none' or 'rotate' (each window turned by a multiple of pi / 16 and mirrored or not)")
        require(0 <= self.num_threads <= 1024, "learner.num_threads", self.num_threads,
                "must be 0..1024 (0 = torch's default)")
        require(0 <= self.seed < 2**63, "learner.seed", self.seed, "must be a non-negative integer")
        require(self.checkpoint_every_updates >= 1, "learner.checkpoint_every_updates",
                self.checkpoint_every_updates, "must be >= 1")
        require(self.weights_wire_dtype in ("auto", "fp32", "bf16"), "learner.weights_wire_dtype",
                self.weights_wire_dtype, "must be 'auto', 'fp32' or 'bf16' (bf16: for actors that compute in bf16)")
        require(self.keep_checkpoints >= 1, "learner.keep_checkpoints", self.keep_checkpoints, "must be >= 1")
        require(self.publish_every_updates >= 1, "learner.publish_every_updates", self.publish_every_updates,
                "must be >= 1")
        require(math.isfinite(self.max_updates_per_insert) and self.max_updates_per_insert >= 0,
                "learner.max_updates_per_insert", self.max_updates_per_insert, "must be >= 0 (0 = no cap)")
        require(self.min_replay_size >= 1, "learner.min_replay_size", self.min_replay_size,
                "must be >= 1 transition")
