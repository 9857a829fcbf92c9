"""`romannet bench place-geometry`: which places of a held cube onto a stack hold, by offset and turn.

A world of three cubes; the second is picked at its centre and placed exactly onto the first (a 2-stack is
built the same way for the "onto a 2-stack" rows), then the next cube is picked at its centre and placed at
an offset from the top cube's centre (along a face and along the diagonal) and turned against it. A place
holds when the ground-truth stack (actor.sim.tasks.stack_height_from_poses) grew by one. Each cell runs
with the fingers coupled (`sim.coupled_fingers`, one mechanism as on the real hands) and independent, so the
table says how precise a place must be, and what the coupling changes. The primitives are the simulator's
own, given world positions directly so the pixel grid does not blur the offsets.
"""

from __future__ import annotations

import math

from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.scene import yaw_of
from romannet.actor.sim.tasks import stack_height_from_poses
from romannet.common.config import TaskConfig
from romannet.common.config_sim import SimConfig

OFFSETS_M = (0.0, 0.005, 0.01, 0.015, 0.02)
TURNS_DEG = (0.0, 22.5, 45.0)
DIRECTIONS_DEG = (0.0, 45.0)  # the offset along a face and along the diagonal


def pick_centre(env: SimEnv, body: int) -> float | None:
    """Pick `body` at its centre, closing across two faces; the held cube's hang, None if it was not held."""
    assert env.prims is not None
    pos, orn = env.scene.pose(body)
    result = env.prims.pick(float(pos[0]), float(pos[1]), env.scene.top_z(body), yaw_of(orn))
    return result.hang_m if result.success else None


def place_on(env: SimEnv, below: int, hang_m: float, offset_m: float, turn_deg: float, direction_deg: float) -> None:
    """Place the held cube offset_m from the top of `below` (direction_deg from its faces), turned turn_deg."""
    assert env.prims is not None
    pos, orn = env.scene.pose(below)
    yaw = yaw_of(orn)
    d = yaw + math.radians(direction_deg)
    x, y = float(pos[0]) + offset_m * math.cos(d), float(pos[1]) + offset_m * math.sin(d)
    env.prims.place(x, y, env.scene.top_z(below), yaw + math.radians(turn_deg), hang_m)


def place_holds(env: SimEnv, seed: int, base: int, offset_m: float, turn_deg: float, direction_deg: float,
                cube_size_m: float) -> bool | None:
    """Build an exact stack of `base` cubes in the world of `seed`, then place one more at the offset and
    turn; did the stack grow? None when the exact stack could not be built (that world is skipped)."""
    env.reset(seed)
    cubes = list(env.scene.objects)
    below = cubes[0]
    for k in range(1, base + 1):
        hang = pick_centre(env, cubes[k])
        if hang is None:
            return None
        last = k == base
        place_on(env, below, hang, offset_m if last else 0.0, turn_deg if last else 0.0,
                  direction_deg if last else 0.0)
        if not last:
            if stack_height_from_poses(env.scene, cube_size_m) != k + 1:
                return None
            below = cubes[k]
    return stack_height_from_poses(env.scene, cube_size_m) == base + 1


def place_table(hand: str, cube_size_m: float, coupled: bool, robot: str = "gripper", seeds: tuple[int, ...] = (0, 1),
                offsets_m: tuple[float, ...] = OFFSETS_M, turns_deg: tuple[float, ...] = TURNS_DEG) -> dict:
    """{"rows": [[base, offset_m, [[held, tried] per turn]]...]}: places onto a lone cube (base 1) and a 2-stack."""
    sim = SimConfig(hand=hand, robot=robot, num_stacking_cubes=3, coupled_fingers=coupled)  # type: ignore[arg-type]
    env = SimEnv(task=TaskConfig(kind="stacking", cube_size_m=cube_size_m), sim=sim)
    rows = []
    try:
        for base in (1, 2):
            for off in offsets_m:
                cells = []
                for turn in turns_deg:
                    outcomes = [place_holds(env, s, base, off, turn, d, cube_size_m)
                                for s in seeds for d in DIRECTIONS_DEG]
                    tried = [o for o in outcomes if o is not None]
                    cells.append([sum(tried), len(tried)])
                rows.append([base, off, cells])
    finally:
        env.close()
    return {"hand": hand, "cube_size_m": cube_size_m, "coupled_fingers": coupled, "turns_deg": list(turns_deg),
            "rows": rows}


def run_place_geometry_benchmark(hands: tuple[str, ...] = ("panda", "rg2"), cube_sizes_m: tuple[float, ...] = (0.04,),
                                 robot: str = "gripper", seeds: tuple[int, ...] = (0, 1)) -> dict:
    """One table per (hand, cube size, coupled or not); see the module docstring."""
    return {"robot": robot, "seeds": list(seeds),
            "tables": [place_table(h, c, coupled, robot, seeds) for h in hands for c in cube_sizes_m
                       for coupled in (True, False)]}


def markdown(result: dict) -> str:
    """Held / tried per turn, one column group per (hand, cube size, fingers)."""
    tables = result["tables"]
    head = " | ".join(f"{t['hand']}, {100 * t['cube_size_m']:g} cm, {'coupled' if t['coupled_fingers'] else 'independent'}"
                      f" fingers: " + " / ".join(f"{a:g}" for a in t["turns_deg"]) + " deg" for t in tables)
    lines = [f"| onto | offset from the top's centre | {head} |", "|---" * (len(tables) + 2) + "|"]
    for i, (base, off, _) in enumerate(tables[0]["rows"]):
        cells = " | ".join(" ".join(f"{h}/{n}" for h, n in t["rows"][i][2]) for t in tables)
        lines.append(f"| {'a lone cube' if base == 1 else 'a 2-stack'} | {100 * off:g} cm | {cells} |")
    return "\n".join(lines)
