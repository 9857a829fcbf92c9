"""One typed, frozen config dataclass per component, and the root Config that groups them.

Load with `load_config(path, overrides)`; a bad value raises ConfigError naming the field, the value and
what is allowed. `write_toml(cfg, path)` saves the resolved config (every run does).
Later components (sim, replay, learner, actor) add their own section here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import tomllib

from .config_actor import ActorConfig
from .config_calibration import CalibrationConfig
from .config_learner import LearnerConfig
from .config_pacing import check_pacing
from .config_replay import ReplayConfig
from .config_robot import RealSenseConfig, RobotConfig
from .config_sim import SimConfig
from .configbase import apply_overrides, drop_retired, from_dict, read_recipe, read_toml, require
from .errors import ConfigError

PRIMITIVES = ("push", "pick", "place")
# Removed fields and the value that kept their code path off: a saved config (a run's config.toml, a
# checkpoint, a model package, an MCAP episode) still names them, and loads if it has that value.
RETIRED: dict[str, Any] = {
    "actor.demo_actions": 0,
    "model.dropout": 0.0,
    "learner.train_rotation_on_success_only": True,
    "replay.group_commit": True,
    "learner.augment_rotation": False,
    "model.angle_bins": 0,
    "learner.rotation_failure_weight": 0.0,
    "model.global_context": False,
    "exploration.q_smoothing_sigma_px": 0.0,
    "reward.place_reward": "tallest",
    "reward.place_centring": False,
    "exploration.action_mask": False,
    "exploration.mask_min_height_m": 0.01,
    "exploration.mask_pick_reach_px": 5,
    "exploration.mask_push_reach_px": 25,
}
# Fields a saved config may lack, and what it ran with then: it was saved before the field existed, or while
# samples_per_insert's "no ratio limit" was an unset value that TOML cannot write. A saved config fills them in
# (a recipe does not: there a missing field means today's default, which may differ).
SAVED_WITHOUT: dict[str, Any] = {
    "model.rotation_harmonics": 1,
    "replay.samples_per_insert": 0.0,
    "sim.coupled_fingers": False,
    "exploration.pick_clearance": False,
    "exploration.pick_angle": "net",
    "model.pick_angle_bins": 0,
    "exploration.pick_centre": False,
}


@dataclass(frozen=True)
class WorkspaceConfig:
    """The square the heightmaps cover, in the robot base frame (metres), and their resolution."""

    x_min_m: float = 0.276
    x_max_m: float = 0.724
    y_min_m: float = -0.224
    y_max_m: float = 0.224
    z_min_m: float = 0.0  # height of the workspace floor (table or bin bottom)
    z_max_m: float = 0.4  # points above this are ignored (e.g. the arm itself)
    resolution_m: float = 0.002  # metres per heightmap pixel

    def __post_init__(self) -> None:
        require(self.x_max_m > self.x_min_m, "workspace.x_max_m", self.x_max_m, "must be greater than x_min_m")
        require(self.y_max_m > self.y_min_m, "workspace.y_max_m", self.y_max_m, "must be greater than y_min_m")
        require(self.z_max_m > self.z_min_m, "workspace.z_max_m", self.z_max_m, "must be greater than z_min_m")
        require(0 < self.resolution_m <= 0.05, "workspace.resolution_m", self.resolution_m,
                "must be in (0, 0.05] metres per pixel (the paper uses 0.002)")
        for name, extent in (("x", self.x_max_m - self.x_min_m), ("y", self.y_max_m - self.y_min_m)):
            px = extent / self.resolution_m
            require(abs(px - round(px)) < 1e-6 and round(px) % 4 == 0, f"workspace.{name}_max_m", extent,
                    f"the {name} extent / resolution_m must be a whole multiple of 4 pixels "
                    f"(RoManNet downsamples twice by 2); got {px:.3f} px")

    @property
    def height_px(self) -> int:
        """Heightmap rows (along y)."""
        return round((self.y_max_m - self.y_min_m) / self.resolution_m)

    @property
    def width_px(self) -> int:
        """Heightmap columns (along x)."""
        return round((self.x_max_m - self.x_min_m) / self.resolution_m)


@dataclass(frozen=True)
class CameraConfig:
    """Pinhole intrinsics of the RGB-D camera (defaults close to VPG's simulated camera)."""

    width_px: int = 640
    height_px: int = 480
    fx_px: float = 618.62
    fy_px: float = 618.62
    cx_px: float = 320.0
    cy_px: float = 240.0
    near_m: float = 0.01
    far_m: float = 10.0

    def __post_init__(self) -> None:
        require(self.width_px > 0, "camera.width_px", self.width_px, "must be a positive number of pixels")
        require(self.height_px > 0, "camera.height_px", self.height_px, "must be a positive number of pixels")
        require(self.fx_px > 0 and self.fy_px > 0, "camera.fx_px", (self.fx_px, self.fy_px),
                "focal lengths must be positive (pixels)")
        require(0 < self.near_m < self.far_m, "camera.near_m", self.near_m, "must satisfy 0 < near_m < far_m")

    @property
    def intrinsics(self) -> tuple[tuple[float, float, float], ...]:
        return ((self.fx_px, 0.0, self.cx_px), (0.0, self.fy_px, self.cy_px), (0.0, 0.0, 1.0))


@dataclass(frozen=True)
class TaskConfig:
    """What the agent is asked to do; decides the allowed primitives and how progress is measured."""

    kind: Literal["clutter", "arrangement", "stacking"] = "clutter"
    use_push: bool = True  # tasks without push run PickNet only while not holding
    goal_stack_height: int = 4  # stacking only: number of cubes in the goal stack
    cube_size_m: float = 0.05  # stacking only: edge of the cubes; the stack height is measured in it, and the
    # simulator's stacking cubes are this size (VPG's cube block is 5 cm)
    # Stacking: a place goes to the centre of the top face under the chosen pixel (common.stack.top_face_centre,
    # read off the heightmap, the same on a real robot) instead of the pixel itself. Frozen places that fell
    # off aimed a median 1.9 cm from the centre of the cube under them, where the heightmap puts every cube
    # top's centre within 0.3 cm (docs/journal.md). The policy still chooses where to place.
    place_on_top_centre: bool = False

    def __post_init__(self) -> None:
        require(2 <= self.goal_stack_height <= 5, "task.goal_stack_height", self.goal_stack_height,
                "must be 2..5 (the paper's stacking goals)")
        require(0.01 <= self.cube_size_m <= 0.2, "task.cube_size_m", self.cube_size_m, "must be 0.01..0.2 m")

    @property
    def primitives(self) -> tuple[str, ...]:
        """Primitives the policy may use in this task."""
        if self.kind == "stacking":
            return ("push", "pick", "place") if self.use_push else ("pick", "place")
        return ("push", "pick") if self.use_push else ("pick",)


PICK_ANGLE_BINS = (0, 4, 8, 16, 32)


@dataclass(frozen=True)
class ModelConfig:
    """RoManNet architecture (three GR-ConvNet variants) and the inference numerics of the actor."""

    channels: int = 32  # GR-ConvNet width after the first 9x9 conv (32 gives ~1.9 M parameters per net)
    residual_blocks: int = 5
    # Rotation head: 1 = (cos k theta, sin k theta) as GR-ConvNet (k = 1 push, 2 pick/place); 2 = also the
    # second harmonic (cos 2k theta, sin 2k theta), which stays trainable when two grasps 90 degrees apart are
    # both right (a cube: the first harmonic's targets cancel there; see common/model.py). 2 raised pick
    # success at 30 blocks on each of 3 seeds (docs/results.md).
    rotation_harmonics: int = 2
    # Initial Q head: "default" = PyTorch's init (Q maps start with peaks of about +-2 that the greedy argmax
    # finds, while returns lie in [0, 2] and the support losses train them down only where an action was
    # tried); "small" = that init times 0.01, so every Q map starts within a few hundredths of 0, below any
    # reward, and its peaks come from what was learned. (Not zero: a flat map gives the argmax and the
    # exploration candidates no order but the pixel index, and failures, labelled 0, give it no gradient.)
    q_head_init: Literal["default", "small"] = "small"
    # The pick net's Q per closing angle: 0 = one Q per pixel, the angle read from the rotation head (trained by
    # regression toward successful angles only, it never learns which angles fail: at lone cubes the clutter
    # recipe's head points anywhere between square and diagonal, docs/journal.md); K = a Q per pixel at each
    # closing angle k pi / K, as VPG's and the paper's code have per input rotation, from one pass: two
    # harmonics of the angle per pixel (common/model.py), so every pick trains every angle. The argmax takes
    # pixel and angle together (with the pick clearance rule, among the clear ones).
    pick_angle_bins: int = 0
    # Inference numerics: "auto" picks bf16 where the CPU computes it natively, else int8 where oneDNN runs it
    # with AVX2 or more, else fp32; "int8": the trunk in int8 (common/int8net.py, near ties rerun in fp32).
    precision: Literal["auto", "fp32", "bf16", "int8"] = "auto"
    channels_last: bool = True
    num_threads: int = 0  # 0 = torch's default (one per core)

    def __post_init__(self) -> None:
        require(4 <= self.channels <= 256, "model.channels", self.channels, "must be 4..256")
        require(0 <= self.residual_blocks <= 20, "model.residual_blocks", self.residual_blocks, "must be 0..20")
        require(self.rotation_harmonics in (1, 2), "model.rotation_harmonics", self.rotation_harmonics,
                "must be 1 (cos/sin of the angle) or 2 (also its second harmonic)")
        require(self.q_head_init in ("default", "small"), "model.q_head_init", self.q_head_init,
                "must be 'default' (PyTorch's init) or 'small' (that init times 0.01: Q maps start near 0)")
        require(self.pick_angle_bins in PICK_ANGLE_BINS, "model.pick_angle_bins", self.pick_angle_bins,
                "must be 0 (the angle from the rotation head) or 4, 8, 16 or 32 (a Q per closing angle)")
        require(self.precision in ("auto", "fp32", "bf16", "int8"), "model.precision", self.precision,
                "must be 'auto' (bf16 where native, else int8 with AVX2, else fp32), 'fp32', 'bf16' or 'int8'")
        require(self.num_threads >= 0, "model.num_threads", self.num_threads, "must be >= 0 (0 = torch default)")


@dataclass(frozen=True)
class RewardConfig:
    """Task Progress based Gaussian reward: R_tpg = max(R_tp, R_tp * G), R_tp = W(phi) X P."""

    push_weight: float = 0.2
    pick_weight: float = 1.0
    place_weight: float = 1.0
    use_progress: bool = True  # False: R = W X (the ablation without task progress)
    use_gaussian: bool = True  # False: R_tp only (the R_tp vs R_tpg ablation)
    sigma_y_px: float = 2.0  # across the gripper axis
    anisotropy: float = 2.0  # sigma_x / sigma_y, x along the gripper's x axis (the paper's ratio)
    kernel_normalization: Literal["peak", "paper"] = "peak"
    kernel_radius_sigmas: float = 3.0  # support: the ellipse of this Mahalanobis radius (r sigma_x by r sigma_y)
    # Where a zero reward (a failed or progress-reversing action) is learned: "kernel" = 0 on the Gaussian's
    # whole support, as a success's reward is spread; "pixel" = at the executed pixel only, as VPG and the
    # R_tp ablation (R_tp (*) G of a zero reward is zero everywhere: the paper does not say where it applies).
    zero_reward_support: Literal["kernel", "pixel"] = "kernel"
    occupied_height_m: float = 0.01  # clutter progress: a pixel is occupied above this height
    progress_tolerance: float = 0.02  # a progress drop larger than this is a reversal (reward 0)

    def __post_init__(self) -> None:
        for name in ("push_weight", "pick_weight", "place_weight"):
            value = getattr(self, name)
            require(0.0 <= value <= 10.0, f"reward.{name}", value, "must be in [0, 10]")
        require(0.1 <= self.sigma_y_px <= 50.0, "reward.sigma_y_px", self.sigma_y_px, "must be 0.1..50 pixels")
        require(1.0 <= self.anisotropy <= 10.0, "reward.anisotropy", self.anisotropy,
                "must be 1..10 (the paper uses sigma_x / sigma_y = 2)")
        require(1.0 <= self.kernel_radius_sigmas <= 6.0, "reward.kernel_radius_sigmas",
                self.kernel_radius_sigmas, "must be 1..6")
        require(self.zero_reward_support in ("kernel", "pixel"), "reward.zero_reward_support",
                self.zero_reward_support, "must be 'kernel' or 'pixel'")
        require(0.0 < self.occupied_height_m < 0.2, "reward.occupied_height_m", self.occupied_height_m,
                "must be in (0, 0.2) m")
        require(0.0 <= self.progress_tolerance < 0.5, "reward.progress_tolerance", self.progress_tolerance,
                "must be in [0, 0.5)")

    @property
    def sigma_x_px(self) -> float:
        """Standard deviation along the gripper's x axis, pixels (sigma_y_px * anisotropy)."""
        return self.sigma_y_px * self.anisotropy

    def weight(self, primitive: str) -> float:
        return {"push": self.push_weight, "pick": self.pick_weight, "place": self.place_weight}[primitive]


@dataclass(frozen=True)
class ExplorationConfig:
    """Loss Adjusted Exploration (the paper's) or VPG's epsilon-greedy schedule (for ablations)."""

    policy: Literal["lae", "epsilon_greedy"] = "lae"
    alpha: float = 0.5
    sigma: float = 0.33  # inverse sensitivity (the authors' code)
    beta: float = 0.25
    initial_rate: float = 0.5
    # A floor under the LAE rate the actors use (VPG's epsilon floor; the recursion itself runs unfloored);
    # 0 = the paper's LAE.
    # LAE follows the loss down: once the nets predict ~0 everywhere and the greedy pick keeps failing on an
    # empty pixel, the loss and with it the rate go to ~0.01 and nothing new is tried (docs/journal.md).
    lae_min_rate: float = 0.1
    top_k: int = 10  # action candidates: the top-k local maxima of each allowed net's Q map
    candidate_min_distance_px: int = 5  # local maxima closer than this are one candidate
    random_angle_prob: float = 0.5  # when exploring, draw the angle uniformly with this probability
    # Pixels within this of an action of the same primitive that failed since the episode's last success are
    # not chosen again (common/failure_memory.py): a greedy policy otherwise repeats a failed pick on the scene
    # it did not change until the episode ends; 10 px beat 20 and 0 on 3 checkpoints (docs/results.md). 0: off.
    failure_memory_px: int = 10
    # Pick only where the open fingers and the hand come down to the grasp height, at the clear closing angle
    # nearest the pick net's own, judged on the depth heightmap by the simulated hand's footprint
    # (common/grasp_clearance.py): a finger landing on a neighbour was most failed clutter picks, and the rule
    # raised the clutter recipe's pick success at 30 blocks from 63.9 % to 81.9 % over 3 seeds (docs/results.md).
    pick_clearance: bool = True
    # The chosen pick's pose (with pick_clearance; without it both have no effect), as the scripted oracle poses
    # its grasps, read from the heightmap. pick_angle: "net", the clear closing angle nearest the pick net's
    # own; "narrowest", the clear angle across which the material under the pick is narrowest (square to a
    # block's faces: the net's angle head does not learn them). pick_centre: then move the pick along that axis
    # to the middle of the material its pads squeeze. Trained with both, the clutter recipe's pick success at
    # 30 blocks rose from 79.9 % to 92.8 % over 3 seeds (docs/results.md).
    pick_angle: Literal["net", "narrowest"] = "narrowest"
    pick_centre: bool = True
    # With pick_centre, also move the pick across its closing axis to the middle of the surface under it, as
    # the oracle grasps a bounding box's middle: a tilted block grasped off its centre of mass turns between
    # the pads and slips out in the lift (most lost clutter picks). Not yet trained with (docs/journal.md).
    pick_centre_across: bool = False
    # With pick_angle = "narrowest", first among the clear angles along which the closing fingers meet only the
    # object: the material counted from the pads' lowest contact (3 mm above the fingertips, not 8) fits the
    # opening and nothing else lies between the open fingers (a finger would push it into the grasp); today's
    # rule where no angle passes. Why: at test time on three policies trained without it, pick success rose from
    # 78.3 % to 85.0 % on 30 novel objects and from 92.2 % to 92.4 % on 30 blocks (docs/journal.md, "What the
    # closing fingers meet"). Off until its 3-seed training sweep is in (journal.md, "Trained with the
    # closing-sweep rule").
    pick_sweep: bool = False
    epsilon_start: float = 0.5  # VPG: eps = max(start * decay^t, min)
    epsilon_decay: float = 0.9998
    epsilon_min: float = 0.1

    def __post_init__(self) -> None:
        require(self.alpha > 0 and math.isfinite(self.alpha), "exploration.alpha", self.alpha, "must be > 0")
        require(self.sigma > 0, "exploration.sigma", self.sigma, "must be > 0 (inverse sensitivity)")
        require(0.0 <= self.beta < 1.0, "exploration.beta", self.beta, "must be in [0, 1)")
        require(0.0 <= self.initial_rate <= 1.0, "exploration.initial_rate", self.initial_rate, "must be in [0, 1]")
        require(0.0 <= self.lae_min_rate <= 1.0, "exploration.lae_min_rate", self.lae_min_rate,
                "must be in [0, 1] (0 = the paper's LAE, no floor)")
        require(1 <= self.top_k <= 1000, "exploration.top_k", self.top_k, "must be 1..1000")
        require(1 <= self.candidate_min_distance_px <= 100, "exploration.candidate_min_distance_px",
                self.candidate_min_distance_px, "must be 1..100")
        require(0.0 <= self.random_angle_prob <= 1.0, "exploration.random_angle_prob", self.random_angle_prob,
                "must be in [0, 1]")
        require(0 <= self.failure_memory_px <= 200, "exploration.failure_memory_px", self.failure_memory_px,
                "must be 0..200 px")
        require(self.pick_angle in ("net", "narrowest"), "exploration.pick_angle", self.pick_angle,
                "must be 'net' or 'narrowest'")
        require(not self.pick_sweep or self.pick_angle == "narrowest", "exploration.pick_sweep", self.pick_sweep,
                "needs pick_angle = 'narrowest' (the sweep chooses among the narrowest rule's angles)")
        require(0.0 <= self.epsilon_min <= self.epsilon_start <= 1.0, "exploration.epsilon_start",
                self.epsilon_start, "must satisfy 0 <= epsilon_min <= epsilon_start <= 1")
        require(0.0 < self.epsilon_decay <= 1.0, "exploration.epsilon_decay", self.epsilon_decay,
                "must be in (0, 1]")


@dataclass(frozen=True)
class Config:
    """The resolved configuration of a run: every component's section."""

    run_id: str = "default"
    seed: int = 0
    workspace: WorkspaceConfig = field(default_factory=WorkspaceConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    actor: ActorConfig = field(default_factory=ActorConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)  # real robot actors only
    realsense: RealSenseConfig = field(default_factory=RealSenseConfig)  # real robot actors only
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)

    def __post_init__(self) -> None:
        require(bool(self.run_id) and all(c.isalnum() or c in "-_" for c in self.run_id), "run_id",
                self.run_id, "must be non-empty and use only letters, digits, '-' and '_' (it is a Zenoh key chunk)")
        require(0 <= self.seed < 2**63, "seed", self.seed, "must be a non-negative integer")
        check_pacing(self.replay, self.learner)
        require(self.exploration.pick_angle == "net" or not self.model.pick_angle_bins, "exploration.pick_angle",
                self.exploration.pick_angle, "must be 'net' when model.pick_angle_bins is set (the angle is the Q's)")


def without_retired(sections: dict[str, Any]) -> dict[str, Any]:
    """Saved config sections (e.g. a checkpoint's) without the RETIRED fields; ConfigError if one is not at the
    value that kept its code path off."""
    return drop_retired(sections, RETIRED)


def as_saved(sections: dict[str, Any]) -> dict[str, Any]:
    """Saved config sections (a run's config.toml, a checkpoint's, a package's, an episode's) as they ran:
    without_retired, and each SAVED_WITHOUT field a present section lacks set to what it ran with."""
    out = without_retired(sections)
    for key, value in SAVED_WITHOUT.items():
        section, name = key.split(".")
        table = out.get(section)
        if isinstance(table, dict) and name not in table:
            out[section] = {**table, name: value}
    return out


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Defaults, then the TOML file (if given, with its `base` chain: configbase.read_recipe), then
    `section.field=value` overrides, validated."""
    data: dict[str, Any] = read_recipe(path) if path is not None else {}
    data = apply_overrides(data, list(overrides))
    return from_dict(Config, without_retired(data))


def load_saved_config(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """A saved config file (a run's config.toml, a model package's) with overrides, as it ran (as_saved)."""
    return from_dict(Config, as_saved(apply_overrides(read_toml(path), list(overrides))))


def load_config_text(text: str, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Like load_saved_config, from TOML text (e.g. the resolved config carried by a checkpoint or an MCAP
    file)."""
    try:
        data: dict[str, Any] = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError("config text", text[:40] + ("…" if len(text) > 40 else ""),
                          f"not valid TOML ({err})") from None
    return from_dict(Config, as_saved(apply_overrides(data, list(overrides))))
