"""Plain frozen dataclasses for every wire message (schema romannet.v1, see romannet.proto).

The rest of the code builds and reads these; common/wire.py turns them into bytes and back. Each class
validates itself on construction (ValueError naming the field), so a message that exists is valid and a
decoder only has to build one. Import them from romannet.common.wire, which re-exports them.

Heightmaps are numpy arrays: color uint8 (h, w, 3) RGB, depth float32 (h, w) metres above the workspace
floor. Classes holding arrays compare by identity (eq=False): numpy arrays have no single truth value.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from .action import Action
from .wire_validate import (
    UINT32_MAX,
    UINT64_MAX,
    check_bool,
    check_float,
    check_heightmaps,
    check_int,
    check_sha256_hex,
    check_text,
    check_token,
)

if TYPE_CHECKING:  # interfaces imports this module: the constructor below only reads their attributes
    from .interfaces import Observation, StepResult

REWARD_LIMIT = 10.0  # |reward| bound: W(phi) <= 10 (config) times X, P <= 1
MAX_BATCH_ITEMS = 4096  # transitions in one sample request / batch
MAX_PRIORITY_ITEMS = 65536  # priorities in one update
MAX_WEIGHTS_BYTES = 1 << 30  # safetensors payload; RoManNet's three nets are ~23 MB in fp32
InsertStatus = Literal["accepted", "duplicate", "rejected"]
INSERT_STATUSES: tuple[str, ...] = ("accepted", "duplicate", "rejected")


def sha256_hex(data: bytes) -> str:
    """SHA-256 of data as 64 lowercase hex digits."""
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True, eq=False)
class TransitionMsg:
    """One executed action with its observations before and after, as an actor publishes it."""

    actor_id: str
    episode_id: str
    step: int  # index of the action within the episode, from 0
    start_ns: int  # action start, ns since the Unix epoch
    end_ns: int  # action end, ns since the Unix epoch (>= start_ns)
    task: str  # task kind, e.g. "clutter"
    color_before: np.ndarray  # uint8 (h, w, 3) RGB
    depth_before: np.ndarray  # float32 (h, w), metres above the floor
    color_after: np.ndarray
    depth_after: np.ndarray
    action: Action
    success: bool  # X: the primitive succeeded
    progress_before: float  # P in [0, 1]
    progress_after: float
    reward: float  # in [-REWARD_LIMIT, REWARD_LIMIT]
    done: bool
    done_reason: str  # identifier if done, "" otherwise
    holding_before: bool
    holding_after: bool
    policy_version: int  # weights version that chose the action
    explore_rate: float  # in [0, 1]
    initial_priority: float | None = None  # finite, >= 0; None: the buffer's choice
    sim_seed: int | None = None  # None on a real robot
    # V(s_{t+1}) as the actor's next decision saw it (the largest Q of the nets allowed in s_{t+1}) and the
    # weights version of that decision; None when no decision followed (episode end, stop) or not sent.
    next_value: float | None = None
    next_value_version: int | None = None

    def __post_init__(self) -> None:
        check_token("actor_id", self.actor_id)
        check_token("episode_id", self.episode_id)
        check_int("step", self.step, 0, UINT32_MAX)
        check_int("start_ns", self.start_ns, 0, UINT64_MAX)
        check_int("end_ns", self.end_ns, self.start_ns, UINT64_MAX)
        check_token("task", self.task)
        h, w = check_heightmaps(self.color_before, self.depth_before, self.color_after, self.depth_after)
        if not isinstance(self.action, Action):
            raise ValueError(f"action must be an Action; got {type(self.action).__name__}")
        check_int("action.row", self.action.row, 0, h - 1)
        check_int("action.col", self.action.col, 0, w - 1)
        # Policies emit angles in (-pi, pi] or [0, 2 pi); anything beyond one turn is a bug upstream.
        check_float("action.angle_rad", self.action.angle_rad, -2 * math.pi, 2 * math.pi)
        check_float("action.q_value", self.action.q_value)
        check_bool("action.explored", self.action.explored)
        for name in ("success", "done", "holding_before", "holding_after"):
            check_bool(name, getattr(self, name))
        check_float("progress_before", self.progress_before, 0.0, 1.0)
        check_float("progress_after", self.progress_after, 0.0, 1.0)
        check_float("reward", self.reward, -REWARD_LIMIT, REWARD_LIMIT)
        if self.done:
            check_token("done_reason", self.done_reason)
        elif self.done_reason != "":
            raise ValueError(f"done_reason = {self.done_reason!r:.80} is invalid: must be empty unless done")
        check_int("policy_version", self.policy_version, 0, UINT64_MAX)
        check_float("explore_rate", self.explore_rate, 0.0, 1.0)
        if self.initial_priority is not None:
            check_float("initial_priority", self.initial_priority, 0.0)
        if self.sim_seed is not None:
            check_int("sim_seed", self.sim_seed, 0, UINT64_MAX)
        if (self.next_value is None) != (self.next_value_version is None):
            raise ValueError("next_value and next_value_version come together or not at all")
        if self.next_value is not None:
            check_float("next_value", self.next_value)
            check_int("next_value_version", self.next_value_version, 0, UINT64_MAX)

    @classmethod
    def from_step(cls, before: Observation, action: Action, result: StepResult, *, actor_id: str,
                  episode_id: str, step: int, start_ns: int, end_ns: int, task: str, policy_version: int = 0,
                  explore_rate: float = 0.0, initial_priority: float | None = None,
                  next_value: float | None = None, next_value_version: int | None = None) -> TransitionMsg:
        """The transition of one executed step: the observation the action was chosen in, the action and
        the environment's result. sim_seed is the scene seed a simulator reports in result.info["seed"]."""
        after, seed = result.observation, result.info.get("seed")
        return cls(
            actor_id=actor_id, episode_id=episode_id, step=step, start_ns=start_ns, end_ns=end_ns, task=task,
            color_before=before.color_hm, depth_before=before.depth_hm, color_after=after.color_hm,
            depth_after=after.depth_hm, action=action, success=bool(result.success),
            progress_before=float(result.progress_before), progress_after=float(result.progress_after),
            reward=float(result.reward), done=bool(result.done), done_reason=result.done_reason if result.done else "",
            holding_before=bool(before.holding), holding_after=bool(after.holding), policy_version=policy_version,
            explore_rate=explore_rate, initial_priority=initial_priority,
            sim_seed=int(seed) if isinstance(seed, int) and seed >= 0 else None,
            next_value=next_value, next_value_version=next_value_version)

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w) of the heightmaps, in pixels."""
        return self.depth_before.shape[0], self.depth_before.shape[1]


@dataclass(frozen=True)
class WeightsAnnouncementMsg:
    """Announces a new weights version; an actor that did not get the Weights put fetches them with a query."""

    version: int
    sha256_hex: str  # of the safetensors bytes
    size_bytes: int
    created_ns: int  # ns since the Unix epoch
    pushed: bool = False  # the Weights were put just before: worth a moment's wait before a fetch

    def __post_init__(self) -> None:
        check_int("version", self.version, 0, UINT64_MAX)
        check_sha256_hex("sha256_hex", self.sha256_hex)
        check_int("size_bytes", self.size_bytes, 1, MAX_WEIGHTS_BYTES)
        check_int("created_ns", self.created_ns, 0, UINT64_MAX)


@dataclass(frozen=True)
class WeightsMsg:
    """A weights version as safetensors bytes; construction checks the SHA-256 (see weightscodec)."""

    version: int
    sha256_hex: str  # of safetensors
    safetensors: bytes

    def __post_init__(self) -> None:
        check_int("version", self.version, 0, UINT64_MAX)
        check_sha256_hex("sha256_hex", self.sha256_hex)
        if not isinstance(self.safetensors, bytes) or not 1 <= len(self.safetensors) <= MAX_WEIGHTS_BYTES:
            raise ValueError(f"safetensors must be 1..{MAX_WEIGHTS_BYTES} bytes; "
                             f"got {type(self.safetensors).__name__} of {len(self.safetensors or b'')} bytes")
        actual = sha256_hex(self.safetensors)
        if actual != self.sha256_hex:
            raise ValueError(f"safetensors SHA-256 is {actual} but the message says {self.sha256_hex}: "
                             "the payload is corrupt or truncated")

    def __repr__(self) -> str:  # the payload is megabytes
        return (f"WeightsMsg(version={self.version}, sha256_hex={self.sha256_hex!r}, "
                f"{len(self.safetensors)} bytes)")


@dataclass(frozen=True)
class ExplorationRateMsg:
    """The exploration rate the learner wants actors to use."""

    version: int  # weights version the rate was computed with
    value: float  # in [0, 1]
    policy: str  # "lae" or "epsilon_greedy"

    def __post_init__(self) -> None:
        check_int("version", self.version, 0, UINT64_MAX)
        check_float("value", self.value, 0.0, 1.0)
        check_token("policy", self.policy)


@dataclass(frozen=True)
class PriorityUpdateMsg:
    """New replay priorities from the learner, one per sampled item."""

    item_ids: tuple[int, ...]
    priorities: tuple[float, ...]  # finite, >= 0

    def __post_init__(self) -> None:
        if len(self.item_ids) != len(self.priorities):
            raise ValueError(f"item_ids has {len(self.item_ids)} entries but priorities has "
                             f"{len(self.priorities)}: they must be equally long")
        if len(self.item_ids) > MAX_PRIORITY_ITEMS:
            raise ValueError(f"{len(self.item_ids)} priorities in one update; at most {MAX_PRIORITY_ITEMS}")
        for i, (item_id, priority) in enumerate(zip(self.item_ids, self.priorities, strict=True)):
            check_int(f"item_ids[{i}]", item_id, 0, UINT64_MAX)
            check_float(f"priorities[{i}]", priority, 0.0)


@dataclass(frozen=True)
class SampleRequestMsg:
    """The learner asks the replay server for a batch."""

    request_id: str
    batch_size: int

    def __post_init__(self) -> None:
        check_token("request_id", self.request_id)
        check_int("batch_size", self.batch_size, 1, MAX_BATCH_ITEMS)


@dataclass(frozen=True, eq=False)
class SampleItem:
    """One sampled transition. `transition` may be the bytes of encode_transition (only when encoding:
    the replay server stores encoded transitions and embeds them without re-encoding PNGs)."""

    item_id: int
    probability: float  # sampling probability P(i), in (0, 1]
    is_weight: float  # importance-sampling weight, finite, > 0
    transition: TransitionMsg | bytes

    def __post_init__(self) -> None:
        check_int("item_id", self.item_id, 0, UINT64_MAX)
        check_float("probability", self.probability, 0.0, 1.0, lo_open=True)
        check_float("is_weight", self.is_weight, 0.0, lo_open=True)
        if not isinstance(self.transition, TransitionMsg | bytes):
            raise ValueError(f"transition must be a TransitionMsg or its encoded bytes; "
                             f"got {type(self.transition).__name__}")


@dataclass(frozen=True, eq=False)
class SampleBatchMsg:
    """The replay server's answer to a SampleRequest; all transitions share one heightmap size."""

    request_id: str
    items: tuple[SampleItem, ...]
    buffer_size: int  # transitions in the buffer when the batch was drawn

    def __post_init__(self) -> None:
        check_token("request_id", self.request_id)
        check_int("buffer_size", self.buffer_size, 0, UINT64_MAX)
        if len(self.items) > MAX_BATCH_ITEMS:
            raise ValueError(f"{len(self.items)} items in one batch; at most {MAX_BATCH_ITEMS}")
        for i, item in enumerate(self.items):
            if not isinstance(item, SampleItem):
                raise ValueError(f"items[{i}] must be a SampleItem; got {type(item).__name__}")
        shapes = {item.transition.shape for item in self.items if isinstance(item.transition, TransitionMsg)}
        if len(shapes) > 1:
            raise ValueError(f"items have heightmaps of different sizes {sorted(shapes)}; "
                             "a batch needs one size")


@dataclass(frozen=True)
class InsertAckMsg:
    """The replay server's answer to an inserted transition."""

    actor_id: str
    episode_id: str
    step: int
    status: InsertStatus
    item_id: int | None = None  # set when accepted or duplicate, None when rejected
    detail: str = ""  # why it was rejected, for people

    def __post_init__(self) -> None:
        check_token("actor_id", self.actor_id)
        check_token("episode_id", self.episode_id)
        check_int("step", self.step, 0, UINT32_MAX)
        if self.status not in INSERT_STATUSES:
            raise ValueError(f"status = {self.status!r:.80} is invalid: must be one of {INSERT_STATUSES}")
        if self.status == "rejected":
            if self.item_id is not None:
                raise ValueError(f"item_id = {self.item_id} is invalid: a rejected insert has no item_id")
        else:
            check_int("item_id", self.item_id, 0, UINT64_MAX)
        check_text("detail", self.detail)
