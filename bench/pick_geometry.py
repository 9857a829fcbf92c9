"""`romannet bench pick-geometry`: which picks of one lone cube a simulated hand holds.

One cube alone on the table; a top-down pick at an offset from its centre along the closing axis and at an
angle between the closing axis and the cube's faces, each in a fresh world built from the same seed (the
same cube pose). The table says how precise a policy must be for each hand and cube size, and so what a
heightmap's resolution costs: a pixel of 2 mm or 4 mm against the margin a hand leaves. The pick is the
simulator's own primitive (guarded descent, force- and speed-limited fingers, lift, hold check), given a
world position directly so the pixel grid does not blur the offsets.
"""

from __future__ import annotations

import math

from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.scene import yaw_of
from romannet.common.config import TaskConfig
from romannet.common.config_sim import SimConfig

OFFSETS_M = (0.0, 0.005, 0.01, 0.015, 0.02, 0.025, 0.03)
ANGLES_DEG = (0.0, 15.0, 30.0, 45.0)


def pick_holds(env: SimEnv, seed: int, offset_m: float, angle_deg: float) -> bool:
    """Build the one-cube world of `seed`, pick at offset_m along the closing axis turned angle_deg from
    the cube's faces; does the hand hold the cube after the lift?"""
    env.reset(seed)
    assert env.prims is not None
    body = env.scene.objects[0]
    pos, orn = env.scene.pose(body)
    closing = yaw_of(orn) + math.radians(angle_deg)
    x = float(pos[0]) + offset_m * math.cos(closing)
    y = float(pos[1]) + offset_m * math.sin(closing)
    return env.prims.pick(x, y, env.scene.top_z(body), closing).success


def hand_table(hand: str, cube_size_m: float, robot: str = "gripper", seed: int = 0,
               offsets_m: tuple[float, ...] = OFFSETS_M, angles_deg: tuple[float, ...] = ANGLES_DEG) -> dict:
    """{"rows": [[offset_m, [held at each angle]]...], "margin_m": {angle: largest offset held from 0 up}}."""
    sim = SimConfig(hand=hand, robot=robot, num_stacking_cubes=1)  # type: ignore[arg-type]
    env = SimEnv(task=TaskConfig(kind="stacking", cube_size_m=cube_size_m), sim=sim)
    try:
        rows = [[off, [pick_holds(env, seed, off, ang) for ang in angles_deg]] for off in offsets_m]
    finally:
        env.close()
    margin = {}
    for j, ang in enumerate(angles_deg):
        held = [off for off, row in rows if row[j]]
        margin[str(ang)] = max((off for off in held if all(r[j] for o, r in rows if o <= off)), default=None)
    return {"hand": hand, "cube_size_m": cube_size_m, "finger_gap_m": 2 * sim.finger_travel_m,
            "angles_deg": list(angles_deg), "rows": rows, "margin_m": margin}


def run_pick_geometry_benchmark(hands: tuple[str, ...] = ("panda", "rg2"), cube_sizes_m: tuple[float, ...] = (0.05, 0.04),
                                robot: str = "gripper", seed: int = 0) -> dict:
    """One table per (hand, cube size); see the module docstring."""
    return {"robot": robot, "seed": seed,
            "tables": [hand_table(h, c, robot, seed) for h in hands for c in cube_sizes_m]}


def markdown(result: dict) -> str:
    """The tables side by side per offset: `Y` held, `n` not, one column group per (hand, cube size)."""
    tables = result["tables"]
    head = " | ".join(f"{t['hand']}, {100 * t['cube_size_m']:g} cm cube: "
                      + " / ".join(f"{a:g}" for a in t["angles_deg"]) + " deg" for t in tables)
    lines = [f"| offset along the closing axis | {head} |", "|---" * (len(tables) + 1) + "|"]
    for i, (off, _) in enumerate(tables[0]["rows"]):
        cells = " | ".join(" ".join("Y" if h else "n" for h in t["rows"][i][1]) for t in tables)
        lines.append(f"| {100 * off:g} cm | {cells} |")
    return "\n".join(lines)
