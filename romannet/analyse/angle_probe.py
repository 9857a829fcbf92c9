"""What a checkpoint's pick rotation head says about cubes: its angle at every lone cube, and at its trained picks.

With a Q per closing angle (model.pick_angle_bins) "the head's angle" is the angle of the net's highest Q at
the pixel (every angle taken as clear).

    romannet analyse angle-probe runs/stack-h4 [--checkpoint DIR] [--episodes 12] [--json]

Two questions about the head that chooses a pick's angle, asked of recorded scenes, not of the policy's choices:
- At a lone cube's centre in the first recorded state of each probed episode (objects found as connected
  heightmap blobs above --min-height whose footprint is 0.5-1.5 x the recorded task.cube_size_m squared),
  how far is the head's closing axis from the cube's faces (pick_offsets.pick_offset, 0-45 deg)? Mean
  cos 4(angle): 1 = square to every cube, -1 = on every diagonal, 0 = no preference.
- At the executed pixel of the recorded successful picks (what the head was trained toward), how far is its
  angle from the executed one, modulo 90 deg (a cube's symmetry; mean cos 4(difference) 1 = the same angle)?
  Greedy and explored picks apart: a greedy pick's angle came from this head (at the weights it acted on),
  so agreement there is partly by construction; an explored pick's angle was drawn at random half the time
  (exploration.random_angle_prob), so agreement there is what the head learned from it. Small here and large
  above = the head fits the picks it was trained on and does not carry that to other cubes.
Episodes probed: up to --episodes, spread evenly over the run. Prints one JSON object (or a line per part).
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path

import cv2
import numpy as np
import torch

from romannet.common.config import load_saved_config
from romannet.common.episode_file import episode_paths
from romannet.common.grasp_clearance import bin_angles
from romannet.common.model import RoManNet, decode_rotation, load_tensors, preprocess
from romannet.common.wire_messages import TransitionMsg
from romannet.learner.checkpoint import latest_checkpoint
from romannet.learner.ckpt_integrity import read_verified

from .phases import recorded_number, recorded_transitions
from .pick_offsets import mean_cos4, pick_offset


def lone_cube_centres(depth_hm: np.ndarray, resolution_m: float, cube_m: float,
                      min_height_m: float = 0.02) -> list[tuple[int, int]]:
    """(row, col) of the centre pixel of every blob above min_height whose footprint is 0.5-1.5 cube_m^2
    (one cube standing alone; stacks count too, touching cubes do not) and whose centre lies on it."""
    depth = np.nan_to_num(np.asarray(depth_hm, dtype=np.float32), nan=0.0)
    n, labels, stats, centres = cv2.connectedComponentsWithStats((depth > min_height_m).astype(np.uint8),
                                                                 connectivity=8)
    area = cube_m ** 2 / resolution_m ** 2
    out = []
    for k in range(1, n):
        if not 0.5 * area <= stats[k, cv2.CC_STAT_AREA] <= 1.5 * area:
            continue
        col, row = (int(round(v)) for v in centres[k])
        if labels[row, col] == k:
            out.append((row, col))
    return out


def pick_angle_map(model: RoManNet, t: TransitionMsg) -> np.ndarray:
    """The pick net's angle (radians) at every pixel of the state before t: its rotation head's, decoded, or
    with a Q per closing angle (model.pick_angle_bins) the angle of its highest Q there."""
    with torch.no_grad():
        q, rot = model.nets["pick"](preprocess(t.color_before, t.depth_before))
    if q.dim() == 4:
        return bin_angles(q.shape[1])[q[0].argmax(dim=0).numpy()]
    return decode_rotation(rot[0].permute(1, 2, 0).numpy(), "pick")


def _angles_summary(deg: list[float], within: str, beyond: str) -> dict:
    return {"count": len(deg), "mean_cos4": mean_cos4(deg),
            "median_deg": round(statistics.median(deg), 1) if deg else None,
            within: sum(d < 10.0 for d in deg), beyond: sum(d > 30.0 for d in deg)}


def probe(model: RoManNet, files: list[Path], min_height_m: float) -> dict:
    """The two parts of the module docstring over the given episode files."""
    to_faces: list[float] = []
    to_executed: dict[bool, list[float]] = {False: [], True: []}  # by explored
    for path in files:
        config_toml, transitions = recorded_transitions(path)
        if not transitions:
            continue
        resolution_m = recorded_number(path, config_toml, "workspace", "resolution_m")
        cube_m = recorded_number(path, config_toml, "task", "cube_size_m")
        first = transitions[0]
        angles = pick_angle_map(model, first)
        for row, col in lone_cube_centres(first.depth_before, resolution_m, cube_m, min_height_m):
            where = pick_offset(first.depth_before, row, col, float(angles[row, col]), resolution_m, min_height_m)
            to_faces.append(where["face_angle_deg"])
        for t in transitions:
            if t.action.primitive == "pick" and t.success:
                a = float(pick_angle_map(model, t)[t.action.row, t.action.col])
                to_executed[bool(t.action.explored)].append(
                    abs(math.degrees(math.remainder(a - t.action.angle_rad, math.pi / 2))))
    return {"episodes": len(files),
            "lone cubes, first states: head angle to the faces":
                _angles_summary(to_faces, "within_10deg", "beyond_30deg"),
            "successful greedy picks: head angle to the executed angle (mod 90 deg)":
                _angles_summary(to_executed[False], "within_10deg", "beyond_30deg"),
            "successful explored picks: head angle to the executed angle (mod 90 deg)":
                _angles_summary(to_executed[True], "within_10deg", "beyond_30deg")}


def spread(files: list[Path], n: int) -> list[Path]:
    """Up to n of the files, evenly spaced, first and last included."""
    if n >= len(files):
        return list(files)
    if n <= 1:
        return files[:n]
    return [files[round(i * (len(files) - 1) / (n - 1))] for i in range(n)]


def probe_run(run: Path, checkpoint: Path | None, episodes: int, min_height_m: float) -> dict:
    """probe() of a checkpoint (default: the run's latest) over up to `episodes` of the run's episode files,
    spread over the run, with the checkpoint it read. FileNotFoundError without a checkpoint."""
    ckpt = checkpoint if checkpoint is not None else latest_checkpoint(run)
    if ckpt is None:
        raise FileNotFoundError(f"no checkpoint in {run / 'checkpoints'}")
    cfg = load_saved_config(run / "config.toml")
    model = RoManNet(cfg.model)
    load_tensors(model, read_verified(ckpt).model_tensors())  # verified, no pickle: what eval loads
    model.eval()
    files = spread(episode_paths([run / "episodes"]), episodes)
    return {"checkpoint": str(ckpt), **probe(model, files, min_height_m)}
