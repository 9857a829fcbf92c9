"""Who acts in an evaluation run: the checkpoint's net (greedy), the scripted oracle, or random valid actions.

The oracle (actor/sim/oracle.py) reads object poses from the simulator: the ceiling of what the simulated
robot can do with these primitives. Random valid actions are the floor: a primitive allowed in the state
(the nets a decision would run), a pixel anywhere in the workspace heightmap and an angle drawn uniformly
from the primitive's range, as exploration draws one; with the pick clearance rule on (exploration.pick_clearance)
a pick is drawn uniformly among the clear (pixel, closing angle) pairs, as a net's decision is bound to them,
so the floor shows what the rule does without a learned choice. Neither learns, so both are evaluated as frozen.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from romannet.common.action import Action
from romannet.common.exploration import ANGLE_RANGE_RAD
from romannet.common.grasp_clearance import bin_angles
from romannet.common.policy import nets_to_run


def random_action(holding: bool, primitives: Sequence[str], shape: tuple[int, int],
                  rng: np.random.Generator, clear: np.ndarray | None = None) -> Action:
    """A uniformly random action the env accepts: an allowed primitive, a heightmap pixel, an angle in range.
    clear: the pick clearance rule's bool (bins, h, w) map (PickClearance.clear); a pick is then one of its clear
    (pixel, closing angle) pairs, drawn uniformly, where there is one."""
    allowed = nets_to_run(holding, primitives)
    primitive = allowed[int(rng.integers(len(allowed)))]
    if primitive == "pick" and clear is not None and clear.any():
        k, row, col = (int(v) for v in np.argwhere(clear)[int(rng.integers(int(clear.sum())))])
        return Action(primitive, row, col, float(bin_angles(clear.shape[0])[k]), 0.0)
    row, col = int(rng.integers(shape[0])), int(rng.integers(shape[1]))
    low, high = ANGLE_RANGE_RAD[primitive]
    return Action(primitive, row, col, float(rng.uniform(low, high)), 0.0)
