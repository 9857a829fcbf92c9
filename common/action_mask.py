"""Common-sense action masks (SPOT's): never choose an action that cannot touch anything.

From the depth heightmap alone (so a real robot masks exactly as the simulator does):

    occupied = depth_hm > min_height_m                      (something stands there)
    pick     = dilate(occupied, disk(pick_reach_px))        (the fingers close on something)
    push     = dilate(occupied, disk(push_reach_px))        (the push can meet something)
    place    = occupied                                     (something below: a place on the floor never
                                                             raises a stack)

A map whose mask is empty everywhere is left unmasked (nothing valid: every action is as good). Masked
pixels get a Q below the map's minimum, so the argmax, the exploration candidates and V(s) = max Q all skip
them; the actor (common.policy.decide) and the learner's bootstrap (learner/trainer.py) apply the same masks.
"""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np
import torch
from torch import Tensor

from .config import ExplorationConfig


def _disk(radius_px: int) -> np.ndarray:
    r = np.arange(-radius_px, radius_px + 1)
    return ((r[:, None] ** 2 + r[None, :] ** 2) <= radius_px ** 2).astype(np.uint8)


def action_masks(depth_hm: np.ndarray, primitives: Iterable[str], cfg: ExplorationConfig) -> dict[str, np.ndarray]:
    """{primitive: bool (h, w) mask of the pixels where the action can touch something} (module docstring)."""
    occupied = (np.asarray(depth_hm) > cfg.mask_min_height_m).astype(np.uint8)
    masks: dict[str, np.ndarray] = {}
    for prim in primitives:
        if prim == "place":
            mask = occupied.astype(bool)
        else:
            radius = cfg.mask_pick_reach_px if prim == "pick" else cfg.mask_push_reach_px
            mask = cv2.dilate(occupied, _disk(radius)).astype(bool) if radius > 0 else occupied.astype(bool)
        masks[prim] = mask if mask.any() else np.ones_like(mask)
    return masks


def masked_q(q: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """q with the masked-out pixels set just below its smallest valid value (finite, so the argmax and the
    local-maximum search work unchanged)."""
    if mask.all():
        return q
    floor = float(q[mask].min()) - 1.0
    return np.where(mask, q, np.float32(floor)).astype(q.dtype, copy=False)


def masked_max(q: Tensor, depth_hms: np.ndarray, primitive: str, cfg: ExplorationConfig) -> list[float]:
    """max Q over the valid pixels of each (h, w) map of a batch q (n, h, w), masks from depth_hms (n, h, w)."""
    out = []
    for qi, depth in zip(q, depth_hms, strict=True):
        mask = torch.from_numpy(action_masks(depth, (primitive,), cfg)[primitive]).to(qi.device)
        out.append(float(qi[mask].max()))
    return out
