"""The learner's training loss as small pure functions over one primitive's batch of k items.

Per item i, in the executed primitive's net: Q map Q_i (h, w), rotation map r_i (2H, h, w), the TPG label
label_i on its support S_i (learner.targets.q_label), the target Y_i at the executed pixel a_i, the rotation
target rho_i with its weight w_i (learner.targets.rotation_targets):

    Huber(e)  = 0.5 e^2 if |e| <= delta else delta (|e| - 0.5 delta)                     huber
    L_Q,i     = sum over S_i of Huber(Q_i - label_i)        ("sum"; "mean": divided by |S_i|)     q_loss
    L_t,i     = Huber(Q_i(a_i) - Y_i)                       the paper's loss at a_i       executed_pixel_loss
    L_rot,i   = w_i ||r_i(a_i) - rho_i||^2                  at a_i                        rotation_pixel_loss
              = w_i mean over S_i of ||r_i - rho_i||^2      over the support              rotation_kernel_loss
    L_i       = L_Q,i + lambda_rot L_rot,i (+ lambda_t L_t,i where lambda_t > 0)          item_loss
    objective = sum_i w^IS_i L_i                            the trainer divides by the batch size

The paper trains Huber(Q(s_t, a_t) - Y_t) alone (L_t); the support loss L_Q carries the TPG reward's
neighbourhood, the rotation loss trains the head the paper leaves unspecified (design.md, section 1).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def huber(error: Tensor, delta: float = 1.0) -> Tensor:
    """Element-wise Huber loss of the paper: 0.5 e^2 for |e| <= delta, delta (|e| - 0.5 delta) beyond."""
    return F.huber_loss(error, torch.zeros_like(error), reduction="none", delta=delta)


def support_loss(q: Tensor, label: Tensor, support: Tensor, delta: float, reduction: str) -> Tensor:
    """Huber(q - label) summed ("sum") or averaged ("mean") over the support; q, label, support (h, w)."""
    per_pixel = huber(q - label, delta) * support
    if reduction == "sum":
        return per_pixel.sum()
    if reduction == "mean":
        return per_pixel.sum() / support.sum().clamp_min(1)
    raise ValueError(f"reduction = {reduction!r} must be 'sum' or 'mean'")


def q_loss(q: Tensor, label: Tensor, support: Tensor, delta: float, reduction: str) -> Tensor:
    """L_Q per item (k,): support_loss of each (h, w) map of q, label, support (k, h, w).

    Item by item, so each item's sum runs over its own map in the same order whatever the batch holds."""
    return torch.stack([support_loss(q[k], label[k], support[k], delta, reduction) for k in range(len(q))])


def executed_pixel_loss(q_exec: Tensor, y: Tensor, delta: float) -> Tensor:
    """L_t per item (k,): Huber(Q(s_t, a_t) - Y_t) at the executed pixel, the paper's loss (and LAE's L)."""
    return huber(q_exec - y, delta)


def rotation_pixel_loss(rot_exec: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """L_rot per item (k,) at the executed pixel: w ||r(a) - rho||^2; rot_exec, target (k, 2H), weight (k,)."""
    return ((rot_exec - target) ** 2).sum(dim=1) * weight


def rotation_kernel_loss(rot: Tensor, target: Tensor, weight: Tensor, support: Tensor) -> Tensor:
    """L_rot per item (k,) over the label's support: w mean_S ||r - rho||^2; rot (k, 2H, h, w), target (k, 2H),
    support (k, h, w). The action poses around the executed pixel share its angle, as GR-ConvNet's angle
    maps are trained over a grasp's region."""
    sq = ((rot - target[:, :, None, None]) ** 2).sum(dim=1)
    return (sq * support).sum(dim=(1, 2)) / support.sum(dim=(1, 2)).clamp_min(1) * weight


def item_loss(q_losses: Tensor, rotation_losses: Tensor, rotation_weight: float, pixel_losses: Tensor,
              pixel_weight: float) -> Tensor:
    """L per item (k,): L_Q + lambda_rot L_rot, plus lambda_t L_t where lambda_t > 0 (0 leaves the executed
    pixel to the support loss alone, and out of the graph)."""
    loss = q_losses + rotation_weight * rotation_losses
    if pixel_weight > 0:
        loss = loss + pixel_weight * pixel_losses
    return loss


def weighted_sum(is_weights: Tensor, item_losses: Tensor) -> Tensor:
    """sum_i w^IS_i L_i: prioritized replay's importance-sampling correction of each item's loss."""
    return (is_weights * item_losses).sum()
