"""How well `romannet mcap rescore` reproduces the simulator's own X, P and R on real simulated episodes.

    python -m romannet.bench.rescore_agreement --json --episodes 4 --random 0.3

Records episodes with the actor's recorder (actor/recorder.py), the floating gripper at 64x64, driving the
simulator with the scripted oracle mixed with uniformly random valid actions (share --random, so there are
failures to judge), then rescores every file under the recorded configuration with each X rule of
romannet/mcaptools/rescoring.py and counts, per task and primitive, the steps whose X and R match what the
simulator recorded. With "recorded" X, P and R are the simulator's own functions of the heightmap, but of the
heightmap as stored (depth in 1e-5 m units), so a pixel right at reward.occupied_height_m can flip:
`max_abs_dr_same_x` shows how far R moves for that reason. "heightmap" and "auto" show what judging X
from heightmaps costs. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np

from romannet.actor.recorder import EpisodeRecorder, step_record
from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.oracle import oracle_action
from romannet.common.action import Action, pixel_to_position
from romannet.common.config import Config, load_config
from romannet.common.configbase import dumps_toml
from romannet.common.episode_file import read_episode
from romannet.common.wire import TransitionMsg, encode_transition
from romannet.mcaptools.rescore import RescoreSettings, rescore_file
from romannet.mcaptools.rescoring import SuccessRule
from romannet.mcaptools.steps import parse_transition, primitive_of

SETS = ["workspace.resolution_m=0.007", 'sim.robot="gripper"', "sim.num_objects=6", "sim.max_steps=20",
        "camera.width_px=160", "camera.height_px=120", "camera.fx_px=154.655", "camera.fy_px=154.655",
        "camera.cx_px=80.0", "camera.cy_px=60.0", "task.goal_stack_height=3"]


def _random_action(env: SimEnv, rng: np.random.Generator) -> Action:
    allowed = [p for p in env.primitives if (p == "place") == env.holding]
    return Action(str(rng.choice(allowed)), int(rng.integers(env.ws.height_px)), int(rng.integers(env.ws.width_px)),
                  float(rng.uniform(-math.pi, math.pi)), 0.0, explored=True)


def record(cfg: Config, path: Path, seed: int, random_share: float) -> int:
    """One episode to `path`; returns its steps."""
    rng = np.random.default_rng(seed)
    with SimEnv.from_config(cfg) as env:
        obs = env.reset(seed)
        rec = EpisodeRecorder(path, {"run_id": cfg.run_id, "actor_id": "bench", "episode_id": f"ep{seed:06d}",
                                     "task": cfg.task.kind, "seed": seed}, dumps_toml(cfg), record_camera=False)
        t_ns, step = 1_700_000_000_000_000_000, 0
        try:
            rec.write_observation(obs, t_ns)
            while True:
                action = _random_action(env, rng) if rng.random() < random_share else oracle_action(env)
                result = env.step(action)
                t_ns += 10**9
                msg = TransitionMsg.from_step(obs, action, result, actor_id="bench", episode_id=f"ep{seed:06d}",
                                              step=step, start_ns=t_ns - 10**9, end_ns=t_ns, task=cfg.task.kind,
                                              explore_rate=random_share)
                position_m = list(pixel_to_position(action.row, action.col, obs.depth_hm, cfg.workspace))
                rec.write_observation(result.observation, t_ns)
                rec.write_step(encode_transition(msg), step_record(msg, position_m, result.detail, info=result.info),
                               t_ns)
                obs, step = result.observation, step + 1
                if result.done:
                    return step
        finally:
            rec.close({"steps": step})


def agreement(paths: list[Path], source: str) -> dict:
    """Per primitive: steps, X matches and R matches (|dR| < 1e-9) between the recording and a rescore."""
    counts: Counter[str] = Counter()
    max_dr: dict[str, float] = {}
    for path in paths:
        result = rescore_file(path, RescoreSettings(rule=SuccessRule(source)), out_dir=None)
        for old_msg, new_bytes in zip(read_episode(path).of("/transition"), result.transitions, strict=True):
            old, new = parse_transition(old_msg.data), parse_transition(new_bytes)
            p = primitive_of(old)
            counts[f"{p}_steps"] += 1
            counts[f"{p}_x_match"] += int(old.success == new.success)
            counts[f"{p}_r_match"] += int(abs(old.reward - new.reward) < 1e-9)
            counts[f"{p}_recorded_successes"] += int(old.success)
            if old.success == new.success:  # R differences not caused by X: P from the stored heightmaps
                max_dr[f"{p}_max_abs_dr_same_x"] = max(max_dr.get(f"{p}_max_abs_dr_same_x", 0.0),
                                                       round(abs(old.reward - new.reward), 6))
    return dict(sorted({**counts, **max_dr}.items()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=4, help="episodes per task (default 4)")
    parser.add_argument("--random", type=float, default=0.3, help="share of random actions (default 0.3)")
    parser.add_argument("--tasks", default="clutter,stacking")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    out: dict = {"episodes_per_task": args.episodes, "random_share": args.random, "config": SETS, "tasks": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for task in args.tasks.split(","):
            cfg = load_config(None, [*SETS, f'task.kind="{task}"', f'run_id="agree-{task}"'])
            paths = [Path(tmp) / task / f"ep{seed:06d}.mcap" for seed in range(args.episodes)]
            steps = sum(record(cfg, path, seed, args.random) for seed, path in enumerate(paths))
            out["tasks"][task] = {"steps": steps, **{s: agreement(paths, s) for s in ("recorded", "auto", "heightmap")}}
    sys.stdout.write(json.dumps(out, indent=None if args.json else 2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
