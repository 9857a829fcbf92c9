"""The learner's target math as small pure functions (paper: "Learning the Action-Value Functions").

    Y_t   = R_tp + eta * gamma * V(s_{t+1})        eta = 1 iff R_tp > 0 (future value only through success)
    V     = max over the primitives allowed in s_{t+1} of max over pixels of Q   (0 at episode end)
    label = R_tpg + eta * gamma * V   on the support of the TPG kernel, undefined (no loss) elsewhere
    loss  = Huber(Q - label) over the support, in the executed primitive's net only (learner/losses.py)

How the label map carries Y: `common.reward.tpg_label` gives R_tpg = max(R_tp, R_tp (*) G) around the
executed pixel, which equals R_tp *at* the executed pixel for either kernel normalisation. Adding the same
constant eta*gamma*V on the whole support makes the label at the executed pixel exactly R_tp + eta*gamma*V
= Y, and its neighbours R_tp*G + eta*gamma*V: the reward is smoothed, the bootstrapped future value is not
(the next state is the same whichever neighbour had been executed). A failed action (R_tp = 0, eta = 0) has
label 0 on the whole support.

Rotation target: on successful actions the rotation head is trained at the executed pixel toward
encode_angle(theta): (cos theta, sin theta) for push, (cos 2 theta, sin 2 theta) for pick/place, plus the
second harmonic with model.rotation_harmonics = 2 (common/model.py says why); rotation_targets gives a
batch's targets and weights (failures weigh 0).

Opposite orientation (paper: "for an antipodal gripper, the pick and place motion primitives are symmetrical
around 0-180 degrees, thus we can pass the gradients for the opposite orientation as well"). VPG's nets
output one Q map per input rotation, so theta + pi is a second output that needs its own gradient. RoManNet
has one output per pixel, and for pick/place both of its labels are invariant under theta -> theta + pi:
the rotation target because cos 2(theta + pi) = cos 2 theta (likewise sin), and the TPG map because the
Gaussian kernel is point symmetric (u -> -u, v -> -v leaves u^2/sx^2 + v^2/sy^2 unchanged), so its support
and values are identical too. The label for theta + pi therefore *is* the label for theta, and training on
it passes the opposite orientation's gradient exactly, with no second term (a second term would only
double-count the same gradient). tests/test_learner_targets.py checks both identities.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from romannet.common.config import RewardConfig
from romannet.common.model import encode_angle
from romannet.common.policy import nets_to_run
from romannet.common.reward import tpg_label


def eta(reward: float) -> float:
    """The reward propagation factor: 1 iff the action earned a positive reward, else 0."""
    if not math.isfinite(reward):
        raise ValueError(f"reward = {reward!r} must be finite")
    return 1.0 if reward > 0 else 0.0


def bootstrap_value(next_q_maps: Mapping[str, np.ndarray | Tensor | float], holding_after: bool,
                    primitives: Sequence[str], done: bool) -> float:
    """V(s_{t+1}): the best Q over the primitives allowed in s_{t+1}; 0 at the episode's end.

    Holding an object only "place" is allowed, otherwise "push" and/or "pick" as the task permits
    (common.policy.nets_to_run, the same rule the actors decide by). `next_q_maps` holds at least those
    primitives' Q maps (any shape) or their maxima; extra keys are ignored.
    """
    if done:
        return 0.0
    best = -math.inf
    for p in nets_to_run(holding_after, primitives):
        if p not in next_q_maps:
            raise ValueError(f"bootstrap needs the {p!r} Q map of s_t+1 (holding={holding_after}); "
                             f"got {sorted(next_q_maps)}")
        q = next_q_maps[p]
        value = float(q.max()) if isinstance(q, (np.ndarray, Tensor)) else float(q)
        if not math.isfinite(value):
            raise ValueError(f"{p} Q map of s_t+1 holds non-finite values: the learner diverged")
        best = max(best, value)
    return best


def return_range(reward_cfg: RewardConfig, gamma: float) -> tuple[float, float]:
    """(lowest, highest) discounted return an action can have: rewards lie in [0, the largest weight W]
    (R_tp = W X P with X in {0, 1} and P in [0, 1]), so returns lie in [0, W / (1 - gamma)]."""
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma = {gamma!r} must be in [0, 1)")
    top = max(reward_cfg.push_weight, reward_cfg.pick_weight, reward_cfg.place_weight)
    return 0.0, top / (1.0 - gamma)


def clip_value(v_next: float, bounds: tuple[float, float]) -> float:
    """V(s_{t+1}) clipped into `bounds` (learner.bootstrap_clip; see return_range)."""
    low, high = bounds
    return float(min(max(v_next, low), high))


def td_target(reward: float, v_next: float, gamma: float) -> float:
    """Y = r + eta(r) * gamma * V(s_{t+1}); r is R_tp (the executed pixel's reward)."""
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma = {gamma!r} must be in [0, 1)")
    if not math.isfinite(v_next):
        raise ValueError(f"v_next = {v_next!r} must be finite")
    return float(reward + eta(reward) * gamma * v_next)


def q_label(shape: tuple[int, int], row: int, col: int, angle_rad: float, reward: float, v_next: float,
            gamma: float, cfg: RewardConfig) -> tuple[np.ndarray, np.ndarray]:
    """(label float32 (h, w), support bool (h, w)): R_tpg + eta*gamma*V on the support, 0 off it.

    label[row, col] == td_target(reward, v_next, gamma) (see the module docstring). `reward` is the
    transition's R_tp = W X P >= 0; a negative reward is rejected as tpg_label does.
    """
    reward_map, support = tpg_label(shape, row, col, angle_rad, reward, cfg)
    future = eta(reward) * gamma * v_next
    if future:
        reward_map = np.where(support, reward_map + np.float32(future), np.float32(0.0)).astype(np.float32)
    return reward_map, support


def rotation_target(angle_rad: float, primitive: str, harmonics: int = 1) -> tuple[float, ...]:
    """The rotation head's target at the executed pixel: encode_angle (2 theta for pick/place), 2 * harmonics
    values (cos, sin of k theta, then of 2k theta with model.rotation_harmonics = 2)."""
    return encode_angle(float(angle_rad), primitive, harmonics)


def rotation_targets(angles_rad: Sequence[float], successes: Sequence[bool], primitive: str,
                     harmonics: int) -> tuple[Tensor, Tensor]:
    """(targets float32 (k, 2 * harmonics), weights float32 (k,)) of k actions of one primitive: row i is
    rotation_target(angle_i), weighted 1 for a success and 0 for a failure (a failed action's angle is not a
    target to imitate, and its opposite measured worse: docs/journal.md)."""
    targets = torch.tensor([rotation_target(a, primitive, harmonics) for a in angles_rad], dtype=torch.float32)
    return targets, torch.tensor([1.0 if ok else 0.0 for ok in successes], dtype=torch.float32)
