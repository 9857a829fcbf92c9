"""RoManNet: three GR-ConvNet variants (PushNet, PickNet, PlaceNet) and their pure helpers.

Each net maps a 4×h×w observation (ImageNet-normalised RGB + scaled depth heightmap) to a pixel-wise Q map
and a pixel-wise rotation encoded as two channels (cos, sin). One forward pass per net, no input rotations.
The layout follows GR-ConvNet (Kumra et al. 2020): 9×9 conv, two stride-2 4×4 convs, residual blocks at 4C,
two stride-2 4×4 transposed convs, a 9×9 conv, then 1×1 heads, so the output is exactly h×w whenever h and
w are multiples of 4.

Rotation encoding: push is directional, so the net encodes θ as (cos θ, sin θ). Pick and place with an
antipodal gripper are symmetric under θ → θ+π, so they encode 2θ: (cos 2θ, sin 2θ), and decode to
θ ∈ (−π/2, π/2]. With k = 1 (push) or 2 (pick/place) the channels are (cos kθ, sin kθ).

With model.rotation_harmonics = 2 the head adds the second harmonic (cos 2kθ, sin 2kθ). Why: the head is
trained by regression toward the executed angle, and for a cube two grasps 90 degrees apart are both right;
in the first harmonic their targets are opposite vectors (2θ and 2θ + π), so the regression averages them
to ~0 and the decoded angle is whatever the bias says (measured: the stacking policies' greedy pick angle
stayed within a few degrees of one value for every cube, docs/journal.md). In the second harmonic both
grasps have the same target, so it learns the cube's faces; decoding takes θ modulo π/k from it and picks,
of the two candidates π/k apart, the one the first harmonic prefers (for a cube either is right; for an
oblong object the first harmonic, which never saw the long-side grasp succeed, tells them apart).

Weights cross processes as a flat {name: tensor} dict (shipped as safetensors by the learner), validated by
`load_tensors`; nothing here unpickles.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch
from torch import Tensor, nn

from .config import PRIMITIVES, ModelConfig
from .errors import DecodeError
from .tensor_checks import all_finite

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
DEPTH_OFFSET_M = 0.01  # depth channel = (d − offset) / scale, VPG's normalisation of the height map
DEPTH_SCALE_M = 0.03
SYMMETRIC_PRIMITIVES = frozenset({"pick", "place"})
Q_HEAD_SCALES = {"default": 1.0, "small": 0.01}  # model.q_head_init: the Q head's initial weights times this
ANGLE_HARMONICS = 2  # harmonics of the closing angle in a per-angle Q (GRConvNet)


class ResidualBlock(nn.Module):
    """Two 3×3 conv + BN with an identity skip (GR-ConvNet's block: no ReLU after the sum)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        self.bn2 = nn.BatchNorm2d(channels)

    def forward(self, x: Tensor) -> Tensor:
        y = torch.relu(self.bn1(self.conv1(x)))
        return x + self.bn2(self.conv2(y))


class GRConvNet(nn.Module):
    """One primitive's net: (B, 4, h, w) → (q, rotation (B, 2 * harmonics, h, w): cos, sin, ...); q is (B, h, w),
    or (B, K, h, w) with angle_bins K: a Q per closing angle k pi / K (model.pick_angle_bins).

    A Q per closing angle is a few harmonics of the angle at each pixel, Q(p, a) = c0(p) + sum over h = 1, 2 of
    c_h(p) cos 2ha + s_h(p) sin 2ha (ANGLE_HARMONICS), evaluated at the K angles by a fixed matrix: every pick,
    at whatever angle and whether it succeeded or failed, trains the pixel's value and its angle preference
    together. (K free maps, one per angle, each learn only from the picks at their angle: the greedy policy kept
    the first angle that succeeded, docs/journal.md.) The second harmonic (4a) holds a cube's quarter-turn
    symmetry, the first (2a) an oblong object's one preferred axis."""

    def __init__(self, channels: int = 32, residual_blocks: int = 5, in_channels: int = 4,
                 rotation_harmonics: int = 1, q_head_scale: float = 1.0, angle_bins: int = 0):
        super().__init__()
        c = channels
        self.conv1 = nn.Conv2d(in_channels, c, 9, padding=4)
        self.bn1 = nn.BatchNorm2d(c)
        self.conv2 = nn.Conv2d(c, 2 * c, 4, stride=2, padding=1)
        self.bn2 = nn.BatchNorm2d(2 * c)
        self.conv3 = nn.Conv2d(2 * c, 4 * c, 4, stride=2, padding=1)
        self.bn3 = nn.BatchNorm2d(4 * c)
        self.res = nn.Sequential(*[ResidualBlock(4 * c) for _ in range(residual_blocks)])
        # (n − 1)·2 − 2·1 + 4 = 2n: kernel 4, stride 2, padding 1 doubles exactly, no output_padding needed.
        self.deconv1 = nn.ConvTranspose2d(4 * c, 2 * c, 4, stride=2, padding=1)
        self.bn4 = nn.BatchNorm2d(2 * c)
        self.deconv2 = nn.ConvTranspose2d(2 * c, c, 4, stride=2, padding=1)
        self.bn5 = nn.BatchNorm2d(c)
        self.conv6 = nn.Conv2d(c, c, 9, padding=4)
        self.q_head = nn.Conv2d(c, 1 + 2 * ANGLE_HARMONICS if angle_bins else 1, 1)
        # (K, 1 + 2H): the per-angle Q from the harmonic channels; a buffer outside the state_dict (fixed).
        self.register_buffer("q_basis", angle_basis(angle_bins) if angle_bins else None, persistent=False)
        self.rot_head = nn.Conv2d(c, 2 * rotation_harmonics, 1)
        if q_head_scale != 1.0:  # model.q_head_init = "small": every Q map starts within a few hundredths of 0
            with torch.no_grad():
                self.q_head.weight.mul_(q_head_scale)
                self.q_head.bias.mul_(q_head_scale)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return self.head(self.features(x))

    def features(self, x: Tensor) -> Tensor:
        """(B, C, h, w): everything up to the last BatchNorm, i.e. the input of `head`."""
        h, w = x.shape[-2:]
        if h % 4 or w % 4:
            raise ValueError(f"input is {h}x{w}: RoManNet needs h and w to be multiples of 4")
        x = torch.relu(self.bn1(self.conv1(x)))
        x = torch.relu(self.bn2(self.conv2(x)))
        x = torch.relu(self.bn3(self.conv3(x)))
        x = self.res(x)
        x = torch.relu(self.bn4(self.deconv1(x)))
        return torch.relu(self.bn5(self.deconv2(x)))

    def head(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The 9x9 conv and the 1x1 heads: stride 1 and no BatchNorm, so on any region of `features` it gives
        the whole map's values wherever they are at least head_radius() from the region's inner edges."""
        x = self.conv6(x)
        q = self.q_head(x)
        if self.q_basis is None:
            return q[:, 0], self.rot_head(x)
        with torch.autocast(x.device.type, enabled=False):  # fp32, as the heads (learner/trainer.py)
            q = torch.einsum("kj,bjhw->bkhw", self.q_basis, q.float())
        return q, self.rot_head(x)

    def head_radius(self) -> int:
        """Pixels of `features` either side of an output pixel that `head` reads (the 9x9 conv's 4)."""
        return self.conv6.kernel_size[0] // 2


class RoManNet(nn.Module):
    """PushNet, PickNet and PlaceNet under stable state_dict keys `nets.<primitive>.<layer>...`."""

    def __init__(self, cfg: ModelConfig | None = None, seed: int = 0):
        super().__init__()
        cfg = cfg or ModelConfig()
        self.cfg = cfg
        # Seeded from a forked generator so construction neither depends on nor disturbs global RNG state.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.nets = nn.ModuleDict({
                p: GRConvNet(cfg.channels, cfg.residual_blocks, rotation_harmonics=cfg.rotation_harmonics,
                             q_head_scale=Q_HEAD_SCALES[cfg.q_head_init], angle_bins=angle_bins(cfg, p))
                for p in PRIMITIVES
            })

    def forward(self, x: Tensor, primitive: str) -> tuple[Tensor, Tensor]:
        return self.nets[primitive](x)


def angle_bins(cfg: ModelConfig, primitive: str) -> int:
    """Closing angles a primitive's net has a Q for: model.pick_angle_bins for pick, else 0 (one Q per pixel)."""
    return cfg.pick_angle_bins if primitive == "pick" else 0


def q_channels(cfg: ModelConfig, primitive: str) -> int:
    """Q maps a primitive's net outputs: one per closing angle (angle_bins), else 1."""
    return angle_bins(cfg, primitive) or 1


def angle_basis(bins: int) -> Tensor:
    """(bins, 1 + 2 * ANGLE_HARMONICS) float32: row k = (1, cos 2a, sin 2a, cos 4a, sin 4a, ...) / sqrt(1 + H) at
    a = k pi / bins. Rows of unit length: a gradient on one angle's Q moves the head's weights as much as a
    single Q map's would (unscaled, three times as much, and the learner's rates diverged)."""
    a = torch.arange(bins, dtype=torch.float64) * (math.pi / bins)
    cols = [torch.ones_like(a)]
    for h in range(1, ANGLE_HARMONICS + 1):
        cols += [torch.cos(2 * h * a), torch.sin(2 * h * a)]
    return (torch.stack(cols, dim=1) / math.sqrt(1 + ANGLE_HARMONICS)).float()


def parameter_count(net: nn.Module) -> int:
    """Number of trainable parameters (BN running statistics are buffers and not counted)."""
    return sum(p.numel() for p in net.parameters() if p.requires_grad)


# ----------------------------------------------------------------------------------------------------------
# Input preprocessing


def preprocess_batch(color_hm: np.ndarray, depth_hm: np.ndarray) -> Tensor:
    """(B,H,W,3) uint8 colour + (B,H,W) float depth in metres → (B,4,H,W) float32 network input."""
    if color_hm.dtype != np.uint8 or color_hm.ndim != 4 or color_hm.shape[-1] != 3:
        raise ValueError(f"color_hm must be uint8 (B,H,W,3); got {color_hm.dtype} {color_hm.shape}")
    if depth_hm.shape != color_hm.shape[:3]:
        raise ValueError(f"depth_hm shape {depth_hm.shape} does not match color_hm {color_hm.shape[:3]}")
    color = torch.from_numpy(np.ascontiguousarray(color_hm)).permute(0, 3, 1, 2).float().div_(255.0)
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    color = (color - mean) / std
    depth = torch.from_numpy(np.asarray(depth_hm, dtype=np.float32)).unsqueeze(1)
    depth = (depth - DEPTH_OFFSET_M) / DEPTH_SCALE_M
    return torch.cat([color, depth], dim=1).contiguous()


def preprocess(color_hm: np.ndarray, depth_hm: np.ndarray) -> Tensor:
    """(H,W,3) uint8 colour + (H,W) float depth in metres → (1,4,H,W) float32 network input."""
    return preprocess_batch(color_hm[None], np.asarray(depth_hm)[None])


# ----------------------------------------------------------------------------------------------------------
# Rotation encoding


def _check_primitive(primitive: str) -> None:
    if primitive not in PRIMITIVES:
        raise ValueError(f"primitive {primitive!r} is not one of {PRIMITIVES}")


def encode_angle(theta, primitive: str, harmonics: int = 1):
    """Rotation target for gripper yaw θ (radians; float, ndarray or Tensor): a tuple of 2 * harmonics.

    push: (cos θ, sin θ); pick/place: (cos 2θ, sin 2θ), so θ and θ+π give the same target. harmonics = 2
    appends (cos 2kθ, sin 2kθ) with k = 1 (push) or 2 (pick/place).
    """
    _check_primitive(primitive)
    if harmonics not in (1, 2):
        raise ValueError(f"harmonics = {harmonics!r} must be 1 or 2")
    k = 2.0 if primitive in SYMMETRIC_PRIMITIVES else 1.0
    mod = torch if isinstance(theta, Tensor) else np if isinstance(theta, np.ndarray) else math
    out: tuple = ()
    for h in range(1, harmonics + 1):
        out += (mod.cos(h * k * theta), mod.sin(h * k * theta))
    return out


def decode_angle(cos, sin, primitive: str):
    """Gripper yaw from the (cos, sin) channels: push θ ∈ (−π, π]; pick/place θ ∈ (−π/2, π/2].

    Accepts floats, ndarrays or Tensors (the rotation head's output need not be unit length).
    """
    _check_primitive(primitive)
    symmetric = primitive in SYMMETRIC_PRIMITIVES
    if isinstance(cos, Tensor):
        a = torch.atan2(sin, cos)
        a = torch.where(a <= -math.pi, a + 2 * math.pi, a)  # atan2(−0, −1) = −π; fold onto the open end
        return a / 2 if symmetric else a
    if isinstance(cos, np.ndarray) or isinstance(sin, np.ndarray):
        a = np.arctan2(sin, cos)
        a = np.where(a <= -np.pi, a + 2 * np.pi, a)
        return a / 2 if symmetric else a
    a = math.atan2(sin, cos)
    if a <= -math.pi:
        a += 2 * math.pi
    return a / 2 if symmetric else a


def decode_rotation(channels: np.ndarray, primitive: str) -> np.ndarray:
    """Gripper yaw from a rotation head's output, channels on the LAST axis: 2 (cos kθ, sin kθ) or 4 (plus the
    second harmonic). Ranges as decode_angle: push (−π, π], pick/place (−π/2, π/2].

    Two harmonics: the second gives θ modulo π/k; of the two candidates π/k apart, the one whose first
    harmonic points the same way as the first-harmonic channels wins (ties, a zero first harmonic: the
    candidate from the second harmonic alone).
    """
    _check_primitive(primitive)
    channels = np.asarray(channels)
    n = channels.shape[-1]
    if n == 2:
        return decode_angle(channels[..., 0], channels[..., 1], primitive)
    if n != 4:
        raise ValueError(f"a rotation output has 2 or 4 channels (1 or 2 harmonics), got {n}")
    k = 2.0 if primitive in SYMMETRIC_PRIMITIVES else 1.0
    fine = np.arctan2(channels[..., 3], channels[..., 2]) / (2 * k)  # θ modulo π/k, in (−π/(2k), π/(2k)]
    agree = channels[..., 0] * np.cos(k * fine) + channels[..., 1] * np.sin(k * fine)
    theta = np.where(agree < 0, fine + np.pi / k, fine)
    period = 2 * np.pi / k  # fold into the primitive's range (−period/2, period/2]
    theta = np.where(theta > period / 2, theta - period, theta)
    return theta


# ----------------------------------------------------------------------------------------------------------
# Weights as a flat tensor dict (the learner ships them as safetensors)


def state_dict_to_tensors(model: nn.Module) -> dict[str, Tensor]:
    """Every parameter and buffer as a detached, contiguous CPU tensor, under the state_dict key."""
    return {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}


def validate_tensors(model: nn.Module, tensors: Mapping[str, Tensor]) -> None:
    """Raise DecodeError unless `tensors` has exactly the model's keys, shapes and dtypes, all finite."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise DecodeError(f"weights do not match RoManNet: missing keys {missing[:5]}"
                          f"{'...' if len(missing) > 5 else ''}, unexpected keys {unexpected[:5]}"
                          f"{'...' if len(unexpected) > 5 else ''}")
    for key, ref in expected.items():
        t = tensors[key]
        if not isinstance(t, Tensor):
            raise DecodeError(f"weights[{key!r}] is a {type(t).__name__}, not a tensor")
        if tuple(t.shape) != tuple(ref.shape):
            raise DecodeError(f"weights[{key!r}] has shape {tuple(t.shape)}, expected {tuple(ref.shape)}")
        if t.dtype != ref.dtype:
            raise DecodeError(f"weights[{key!r}] has dtype {t.dtype}, expected {ref.dtype}")
        if not all_finite(t):
            raise DecodeError(f"weights[{key!r}] contains NaN or infinite values")
        if key.endswith("running_var") and bool((t < 0).any()):
            raise DecodeError(f"weights[{key!r}] has negative variances")


def load_tensors(model: nn.Module, tensors: Mapping[str, Tensor]) -> None:
    """Validate (see `validate_tensors`) and copy `tensors` into `model` in place."""
    validate_tensors(model, tensors)
    model.load_state_dict(dict(tensors), strict=True)
