"""An episode's messages grouped into steps, and the fields of a recorded Transition without its pixels.

The actor records, in this order (actor/recorder.py): the first observation, then per step the Q maps at
the decision, the observation after the action, the /transition and the /step record. So at step k's
/transition the observations seen so far are 0..k+1: the step acted on the second-to-last one and
produced the last one. A file cut after a /transition but before its /step still yields that step, with
record None.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from google.protobuf import message as pb_message

from romannet.common import romannet_pb2 as pb
from romannet.common.episode_file import (
    HEIGHTMAP_COLOR_TOPIC,
    OBSERVATION_TOPICS,
    Q_TOPIC_PREFIX,
    STEP_TOPIC,
    TRANSITION_TOPIC,
    RecordedMessage,
)
from romannet.common.errors import DecodeError

log = logging.getLogger(__name__)

PRIMITIVE_NAMES = {pb.PRIMITIVE_PUSH: "push", pb.PRIMITIVE_PICK: "pick", pb.PRIMITIVE_PLACE: "place"}
Observation = dict[str, RecordedMessage]  # topic -> message, one observation's images


@dataclass(frozen=True)
class RecordedStep:
    """One executed action as recorded: its Transition, /step record, Q maps and observations."""

    transition: RecordedMessage
    record: dict | None
    q_maps: dict[str, RecordedMessage] = field(default_factory=dict)  # primitive -> colormapped Q map PNG
    before: Observation = field(default_factory=dict)
    after: Observation = field(default_factory=dict)


def parse_transition(data: bytes) -> pb.Transition:
    """The protobuf fields of an encoded Transition (pixels stay PNG bytes; use wire.decode_transition for
    the validated, decoded message). Raises DecodeError if the bytes are not a Transition."""
    msg = pb.Transition()
    try:
        msg.ParseFromString(data)
    except pb_message.DecodeError as err:
        raise DecodeError(f"invalid Transition: not a protobuf Transition message ({err})") from err
    return msg


def primitive_of(t: pb.Transition) -> str:
    return PRIMITIVE_NAMES.get(t.action.primitive, "unspecified")


def _json(msg: RecordedMessage) -> dict | None:
    try:
        value = json.loads(msg.data)
    except (UnicodeDecodeError, ValueError) as err:
        log.warning("a /step record is not JSON (%s); ignored", err)
        return None
    return value if isinstance(value, dict) else None


def group_steps(messages: Iterable[RecordedMessage]) -> Iterator[RecordedStep]:
    """RecordedStep per /transition, in recorded order (see the module docstring)."""
    observations: list[Observation] = []  # the last two: before and after the current step
    q_maps: dict[str, RecordedMessage] = {}
    open_step: RecordedStep | None = None
    for msg in messages:
        if msg.topic in OBSERVATION_TOPICS:
            if msg.topic == HEIGHTMAP_COLOR_TOPIC or not observations:
                observations = [*observations[-1:], {}]  # each observation starts with its color heightmap
            observations[-1][msg.topic] = msg
        elif msg.topic.startswith(Q_TOPIC_PREFIX):
            q_maps[msg.topic[len(Q_TOPIC_PREFIX):]] = msg
        elif msg.topic == TRANSITION_TOPIC:
            if open_step is not None:
                yield open_step
            before = observations[-2] if len(observations) >= 2 else {}
            after = observations[-1] if observations else {}
            open_step, q_maps = RecordedStep(msg, None, q_maps, before, after), {}
        elif msg.topic == STEP_TOPIC and open_step is not None:
            yield RecordedStep(open_step.transition, _json(msg), open_step.q_maps, open_step.before,
                               open_step.after)
            open_step = None
    if open_step is not None:
        yield open_step
