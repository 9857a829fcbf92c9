"""Who acts in an evaluation run: the checkpoint's net (greedy), the scripted oracle, or random valid actions.

The oracle (actor/sim/oracle.py) reads object poses from the simulator: the ceiling of what the simulated
robot can do with these primitives. Random valid actions are the floor: a primitive allowed in the state
(the nets a decision would run), a pixel anywhere in the workspace heightmap and an angle drawn uniformly
from the primitive's range, as exploration draws one. Neither learns, so both are evaluated as frozen.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from romannet.common.action import Action
from romannet.common.exploration import ANGLE_RANGE_RAD
from romannet.common.policy import nets_to_run

POLICIES = ("net", "oracle", "random")
SCRIPTED = ("oracle", "random")  # policies that need no checkpoint
DESCRIPTION = {
    "net": "the checkpoint's greedy policy",
    "oracle": "the scripted oracle (reads object poses from the simulator: the ceiling)",
    "random": "uniformly random valid actions (the floor)",
}


def random_action(holding: bool, primitives: Sequence[str], shape: tuple[int, int],
                  rng: np.random.Generator) -> Action:
    """A uniformly random action the env accepts: an allowed primitive, a heightmap pixel, an angle in range."""
    allowed = nets_to_run(holding, primitives)
    primitive = allowed[int(rng.integers(len(allowed)))]
    row, col = int(rng.integers(shape[0])), int(rng.integers(shape[1]))
    low, high = ANGLE_RANGE_RAD[primitive]
    return Action(primitive, row, col, float(rng.uniform(low, high)), 0.0)
