"""Loss Adjusted Exploration (LAE), VPG's epsilon-greedy schedule, and action selection over Q maps.

    f(L)    = (1 - exp(-|alpha L| / sigma)) / (1 + exp(-|alpha L| / sigma)) = tanh(|alpha L| / (2 sigma))
    E_{t+1} = beta f(L_t) + (1 - beta) E_t
    policy  = uniform over the action candidates if xi < E, else argmax over the allowed nets' Q maps

The learner owns an ExplorationRate and pushes its value to the actors; actors call select_action in their
decision path, so it avoids per-call allocations beyond what the maps themselves need.
"""

from __future__ import annotations

import functools
import logging
import math

import cv2
import numpy as np

from .action import Action
from .config import PRIMITIVES, ExplorationConfig

logger = logging.getLogger(__name__)

# Angle ranges of an explored angle: a push has a direction (full turn); a parallel-jaw grasp or place is the
# same after half a turn, so [-pi/2, pi/2) covers every distinct pick/place.
ANGLE_RANGE_RAD: dict[str, tuple[float, float]] = {
    "push": (-math.pi, math.pi),
    "pick": (-math.pi / 2, math.pi / 2),
    "place": (-math.pi / 2, math.pi / 2),
}

Candidate = tuple[str, int, int, float]  # (primitive, row, col, q)


class NonFiniteQError(ValueError):
    """A Q map holds NaN or infinity: the weights that produced it are unusable (a diverged learner)."""


# ------------------------------------------------------------------------------------------ rates
def lae_f(loss: float, alpha: float = 0.5, sigma: float = 0.33) -> float:
    """The paper's Boltzmann-shaped map of a loss to [0, 1): tanh(|alpha loss| / (2 sigma)).

    The tanh form is the same function and stays finite for huge losses (math.tanh saturates at 1.0, an
    infinite loss gives 1.0). A NaN loss means the learner diverged and must not silently set the rate.
    """
    loss = float(loss)
    if math.isnan(loss):
        raise ValueError("loss is NaN: the learner diverged; refusing to update the exploration rate")
    if not (alpha > 0 and math.isfinite(alpha)):
        raise ValueError(f"alpha = {alpha!r} must be a positive finite number")
    if not (sigma > 0 and math.isfinite(sigma)):
        raise ValueError(f"sigma = {sigma!r} must be a positive finite number (inverse sensitivity)")
    return math.tanh(abs(alpha * loss) / (2.0 * sigma))


def lae_update(rate: float, loss: float, cfg: ExplorationConfig) -> float:
    """One LAE step: E_{t+1} = beta f(L_t) + (1 - beta) E_t, in [0, 1]."""
    if not (math.isfinite(rate) and 0.0 <= rate <= 1.0):
        raise ValueError(f"exploration rate = {rate!r} must be in [0, 1]")
    return cfg.beta * lae_f(loss, cfg.alpha, cfg.sigma) + (1.0 - cfg.beta) * rate


def epsilon_greedy_rate(step: int, cfg: ExplorationConfig) -> float:
    """VPG's schedule: max(epsilon_start * epsilon_decay^step, epsilon_min); step = training updates so far."""
    if step < 0:
        raise ValueError(f"step = {step!r} must be >= 0")
    return max(cfg.epsilon_start * cfg.epsilon_decay**step, cfg.epsilon_min)


class ExplorationRate:
    """The learner's exploration rate: LAE from the loss, or the epsilon schedule by update count.

    State is two plain numbers (value, steps) so it checkpoints anywhere; `policy` is taken from the config.
    """

    def __init__(self, cfg: ExplorationConfig):
        self._cfg = cfg
        self._steps = 0
        self._value = cfg.initial_rate if cfg.policy == "lae" else epsilon_greedy_rate(0, cfg)

    @property
    def value(self) -> float:
        """Current probability of exploring, in [0, 1] (LAE: never below exploration.lae_min_rate)."""
        if self._cfg.policy == "lae":
            return max(self._value, self._cfg.lae_min_rate)
        return self._value

    @property
    def steps(self) -> int:
        """Number of update() calls (training steps) so far."""
        return self._steps

    def update(self, loss: float) -> float:
        """Advance one training step with its loss; returns the new rate (the loss is unused by epsilon_greedy)."""
        if self._cfg.policy == "lae":
            new_value = lae_update(self._value, loss, self._cfg)
        elif self._cfg.policy == "epsilon_greedy":
            new_value = epsilon_greedy_rate(self._steps + 1, self._cfg)
        else:  # the config validates policy; this guards a hand-built config
            raise ValueError(f"exploration.policy = {self._cfg.policy!r} must be 'lae' or 'epsilon_greedy'")
        self._steps += 1
        self._value = new_value
        return self.value

    def state_dict(self) -> dict[str, float | int]:
        return {"value": float(self._value), "steps": int(self._steps)}

    def load_state_dict(self, state: dict[str, float | int]) -> None:
        value, steps = float(state["value"]), state["steps"]
        if not (math.isfinite(value) and 0.0 <= value <= 1.0):
            raise ValueError(f"exploration state value = {value!r} must be in [0, 1]")
        if isinstance(steps, bool) or int(steps) != steps or steps < 0:
            raise ValueError(f"exploration state steps = {steps!r} must be a non-negative integer")
        self._value, self._steps = value, int(steps)


# ------------------------------------------------------------------------------------ action selection
@functools.lru_cache(maxsize=16)
def _square_kernel(min_distance_px: int) -> np.ndarray:
    # A rectangular structuring element lets OpenCV run the max filter separably (fast at 224x224).
    return np.ones((2 * min_distance_px + 1, 2 * min_distance_px + 1), dtype=np.uint8)


@functools.lru_cache(maxsize=16)
def _disk(min_distance_px: int) -> np.ndarray:
    """Boolean (2d-1)^2 mask of the offsets closer than d = min_distance_px (Euclidean)."""
    offsets = np.arange(-(min_distance_px - 1), min_distance_px)
    return offsets[:, None] ** 2 + offsets[None, :] ** 2 < min_distance_px**2


def _ordered_primitives(q_maps: dict[str, np.ndarray]) -> list[str]:
    """The maps' primitives in PRIMITIVES order (ties between nets break toward the earlier one)."""
    unknown = set(q_maps) - set(PRIMITIVES)
    if unknown or not q_maps:
        raise ValueError(f"Q map keys {sorted(q_maps)} must be a non-empty subset of {PRIMITIVES}")
    return [p for p in PRIMITIVES if p in q_maps]


def _as_map(q: np.ndarray, name: str, shape: tuple[int, ...] | None) -> np.ndarray:
    q = np.asarray(q)
    if q.ndim != 2 or q.size == 0 or (shape is not None and q.shape != shape):
        raise ValueError(f"{name} map has shape {q.shape}; expected a non-empty 2-D map"
                         + (f" of shape {shape}" if shape is not None else ""))
    return q


def action_candidates(q_maps: dict[str, np.ndarray], k: int, min_distance_px: int) -> list[Candidate]:
    """The top-k local maxima of EACH given net's Q map, pooled and sorted best first.

    Per net, not pooled before the cut: nets start at different Q offsets (random init, or a primitive that
    has earned more reward), and a pooled top-k then holds one primitive only, so exploration would never
    try the other (seen: 129 untrained actions, all picks). With k per net, uniform exploration over the
    candidates tries every allowed primitive. Returns [(primitive, row, col, q), ...]; see _top_k_maxima.
    """
    if k < 1 or min_distance_px < 1:
        raise ValueError(f"k = {k!r} and min_distance_px = {min_distance_px!r} must both be >= 1")
    prims = _ordered_primitives(q_maps)
    shape = _as_map(q_maps[prims[0]], prims[0], None).shape
    pooled: list[Candidate] = []
    for prim in prims:
        _as_map(q_maps[prim], prim, shape)  # same shape for every net
        pooled += _top_k_maxima({prim: q_maps[prim]}, k, min_distance_px)
    order = {prim: i for i, prim in enumerate(prims)}
    return sorted(pooled, key=lambda c: (-c[3], order[c[0]], c[1], c[2]))


def _top_k_maxima(q_maps: dict[str, np.ndarray], k: int, min_distance_px: int) -> list[Candidate]:
    """Top-k local maxima across the given Q maps, best first: [(primitive, row, col, q), ...].

    A pixel is a local maximum of its own map if no pixel within `min_distance_px` (square window) is higher;
    equal-valued maxima (plateaus) closer than `min_distance_px` (Euclidean) in the same map count once, the
    first in (row, col) order. Ties in q order by primitive (PRIMITIVES order), then row, then col, so the
    result is a pure function of the maps. Maps must hold finite values.
    """
    if k < 1 or min_distance_px < 1:
        raise ValueError(f"k = {k!r} and min_distance_px = {min_distance_px!r} must both be >= 1")
    prims = _ordered_primitives(q_maps)
    shape = _as_map(q_maps[prims[0]], prims[0], None).shape
    kernel = _square_kernel(min_distance_px)
    values, keys = [], []
    for i, prim in enumerate(prims):
        q = np.ascontiguousarray(_as_map(q_maps[prim], prim, shape), dtype=np.float32)
        if not np.isfinite(q).all():
            raise NonFiniteQError(f"{prim} Q map holds non-finite values")
        flat = np.flatnonzero(q >= cv2.dilate(q, kernel))  # border is padded with -inf by OpenCV's default
        values.append(q.ravel()[flat])
        keys.append(flat + i * q.size)  # key order = (primitive, row, col)
    all_values, all_keys = np.concatenate(values), np.concatenate(keys)
    order = np.argsort(-all_values, kind="stable")  # stable: equal q keep key order

    # Greedy suppression. Only plateaus need it (a strict maximum has no equal-or-higher pixel within its
    # window), so `taken` marks the disk around each accepted peak; a flat map yields peaks spaced d apart.
    h, w = shape
    taken = np.zeros((len(prims), h, w), dtype=bool)
    disk = _disk(min_distance_px)
    r = min_distance_px - 1
    # Each accepted peak rejects at most disk.sum() - 1 others, so k * disk.sum() candidates always suffice.
    order = order[:k * int(disk.sum())]
    result: list[Candidate] = []
    for key, value in zip(all_keys[order].tolist(), all_values[order].tolist(), strict=True):
        p, pix = divmod(key, h * w)
        row, col = divmod(pix, w)
        if taken[p, row, col]:
            continue
        result.append((prims[p], row, col, value))
        if len(result) == k:
            break
        r0, r1, c0, c1 = max(row - r, 0), min(row + r + 1, h), max(col - r, 0), min(col + r + 1, w)
        taken[p, r0:r1, c0:c1] |= disk[r0 - row + r:r1 - row + r, c0 - col + r:c1 - col + r]
    return result


def _random_angle(primitive: str, rng: np.random.Generator) -> float:
    low, high = ANGLE_RANGE_RAD[primitive]
    return float(rng.uniform(low, high))


def select_action(q_maps: dict[str, np.ndarray], angle_maps: dict[str, np.ndarray], explore_rate: float,
                  cfg: ExplorationConfig, rng: np.random.Generator,
                  masks: dict[str, np.ndarray] | None = None) -> Action:
    """The LAE policy: explore (uniform over action candidates) if xi < explore_rate, else argmax.

    Args:
        q_maps: {primitive: (h, w) float32 Q map} of the nets allowed now (e.g. no "place" unless holding).
        angle_maps: {primitive: (h, w) float32 gripper yaw in radians}, at least the keys of q_maps.
        explore_rate: E in [0, 1] (pushed by the learner).
        cfg: top_k, candidate_min_distance_px and random_angle_prob are used.
        rng: the actor's generator; the same seed and maps give the same action.
        masks: {primitive: bool (h, w)} valid pixels (the failure memory's); the q_maps are already masked
            (common.failure_memory.masked_q) and exploring draws only among valid candidates.

    Exploring picks one of action_candidates(...) uniformly (explored=True); with probability
    cfg.random_angle_prob the angle is drawn uniformly from ANGLE_RANGE_RAD[primitive], else read from that
    net's angle map. Exploiting takes the highest Q over all maps (ties: earlier primitive, then row-major
    first pixel). The angle map value is passed through unwrapped. q_value is the Q at the chosen pixel.
    """
    if not (math.isfinite(explore_rate) and 0.0 <= explore_rate <= 1.0):
        raise ValueError(f"explore_rate = {explore_rate!r} must be in [0, 1]")
    prims = _ordered_primitives(q_maps)
    missing = [p for p in prims if p not in angle_maps]
    if missing:
        raise ValueError(f"angle maps missing for {missing}")

    if rng.random() < explore_rate:
        candidates = action_candidates(q_maps, cfg.top_k, cfg.candidate_min_distance_px)
        if masks is not None:
            candidates = [c for c in candidates if masks[c[0]][c[1], c[2]]] or candidates
        prim, row, col, q = candidates[int(rng.integers(len(candidates)))]
        angle_map = _as_map(angle_maps[prim], f"{prim} angle", np.shape(q_maps[prim]))
        if rng.random() < cfg.random_angle_prob:
            angle = _random_angle(prim, rng)
        else:
            angle = float(angle_map[row, col])
        return Action(prim, row, col, angle, q, explored=True)

    best: tuple[float, str, int] | None = None
    shape = None
    for prim in prims:
        q = _as_map(q_maps[prim], prim, shape)
        shape = q.shape
        flat_idx = int(np.argmax(q))  # NaN counts as the maximum in np.argmax, so one check covers the map
        value = float(q.flat[flat_idx])
        if not math.isfinite(value):
            raise NonFiniteQError(f"{prim} Q map holds non-finite values")
        if best is None or value > best[0]:
            best = (value, prim, flat_idx)
    assert best is not None  # prims is non-empty
    value, prim, flat_idx = best
    row, col = divmod(flat_idx, shape[1])
    angle_map = _as_map(angle_maps[prim], f"{prim} angle", shape)
    return Action(prim, row, col, float(angle_map[row, col]), value, explored=False)
