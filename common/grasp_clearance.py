"""Where a top-down pick's open fingers and hand come down, read from the depth heightmap alone.

A pick whose open finger lands on a neighbour stops high and closes over the object's top (in clutter most
failed picks do: docs/journal.md, "Why clutter picks fail"). The rule here is the one the scripted oracle
(actor/sim/oracle.py) judges its grasps by, on what a robot sees: a pick at pixel p along closing angle a is
clear when nothing under either open finger, nor under the hand less the hand's height above the fingertips,
is higher than the fingers' grasp height at p, and p itself holds material at the pads' height.
`clear_picks` evaluates it for every pixel on `bins` closing angles over half a turn (the hand is
symmetric); a decision then picks only at pixels with a clear angle, at the clear angle nearest the pick
net's own (`nearest_clear_angle`), or (exploration.pick_angle = "narrowest") at the clear angle across which
the material between the fingers is narrowest (`narrowest_clear_bin`: square to a block's faces); with
exploration.pick_centre the pick then moves along its closing axis to the middle of the material its pads
squeeze (`centred_pixel`). With exploration.pick_sweep the narrowest angle is sought first among those along
which the closing fingers meet only the object (`closing_widths(..., sweep=True)`).

Heights are metres above the table (the depth heightmap's values); angles as in common.action: from the x
(column) axis toward the y (row) axis, the finger-closing axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .config import Config

# Where an open finger comes down, from the pick's centre: from the inner face at the finger travel, this
# far outward along the closing axis and this far either side across it (the Panda finger's lower part).
FINGER_OUTWARD_M = 0.02
FINGER_HALF_WIDTH_M = 0.012
# The hand above the fingers: 21 cm along the closing axis, 7 cm across, its underside this far above the
# fingertips.
HAND_HALF_LENGTH_M = 0.105
HAND_HALF_WIDTH_M = 0.035
HAND_ABOVE_TIPS_M = 0.045
# The Panda's fingers squeeze with their lowest centimetre: there must be material at these heights above
# the fingertips (an arch grasped over its hole has material only higher up, and slips: measured).
PAD_HEIGHTS_M = (0.003, 0.008)
DEFAULT_BINS = 16  # closing angles the rule is judged on (over half a turn)
# Neighbouring pixels of one object's top differ by less than this (a 5 cm block tilted 45 degrees: 2 mm a pixel
# at 2 mm pixels); a larger step is an edge, or another object lying against it.
SURFACE_STEP_M = 0.006
CLEAR_M = 0.003  # the fingers reach their grasp height when nothing in their footprint is higher than this above it


@dataclass(frozen=True)
class GripperFootprint:
    """A parallel gripper's open fingers and hand as they come down, and how deep a pick goes."""

    travel_m: float  # each finger's inner face from the centre when open
    pick_depth_m: float  # the fingertips go this far below the surface at the pick's pixel
    tip_floor_m: float  # ... but never lower than this above the table
    finger_outward_m: float = FINGER_OUTWARD_M
    finger_half_width_m: float = FINGER_HALF_WIDTH_M
    hand_half_length_m: float = HAND_HALF_LENGTH_M
    hand_half_width_m: float = HAND_HALF_WIDTH_M
    hand_above_tips_m: float = HAND_ABOVE_TIPS_M
    clear_m: float = CLEAR_M

    def grasp_height(self, surface_m: np.ndarray | float) -> np.ndarray | float:
        """The fingertips' grasp height (m above the table) below a surface at this height."""
        return np.maximum(np.asarray(surface_m) - self.pick_depth_m, self.tip_floor_m)


def zone_max(depth_hm: np.ndarray, resolution_m: float, xy_px: tuple[float, float], angle_rad: float,
             along_m: tuple[float, float], half_width_m: float) -> float:
    """Highest heightmap value in a rectangle: from along_m[0] to along_m[1] from the point xy_px (column,
    row; pixel units) along angle_rad, half_width_m either side of that line; 0 (the table) outside the map."""
    d = np.array([math.cos(angle_rad), math.sin(angle_rad)])
    n = np.array([-math.sin(angle_rad), math.cos(angle_rad)])
    step = 0.5  # pixel
    s = np.arange(along_m[0] / resolution_m, along_m[1] / resolution_m + 1e-9, step)
    t = np.arange(-half_width_m / resolution_m, half_width_m / resolution_m + 1e-9, step)
    pts = np.asarray(xy_px, dtype=np.float64) + s[:, None, None] * d + t[None, :, None] * n
    cols = np.floor(pts[..., 0]).astype(int).ravel()
    rows = np.floor(pts[..., 1]).astype(int).ravel()
    inside = (rows >= 0) & (rows < depth_hm.shape[0]) & (cols >= 0) & (cols < depth_hm.shape[1])
    return float(depth_hm[rows[inside], cols[inside]].max()) if inside.any() else 0.0


def footprint_height(depth_hm: np.ndarray, resolution_m: float, xy_px: tuple[float, float], angle_rad: float,
                     g: GripperFootprint) -> float:
    """The lowest the fingertips come down over xy_px (column, row; pixel units) along angle_rad before an
    open finger or the hand lands on something (m above the table)."""
    travel = (g.travel_m, g.travel_m + g.finger_outward_m)
    fingers = max(zone_max(depth_hm, resolution_m, xy_px, angle_rad, travel, g.finger_half_width_m),
                  zone_max(depth_hm, resolution_m, xy_px, angle_rad + math.pi, travel, g.finger_half_width_m))
    hand = zone_max(depth_hm, resolution_m, xy_px, angle_rad, (-g.hand_half_length_m, g.hand_half_length_m),
                    g.hand_half_width_m)
    return max(fingers, hand - g.hand_above_tips_m)


def _rotation(angle_rad: float, shape: tuple[int, int], canvas: int) -> np.ndarray:
    """2x3 affine from a canvas pixel (u along the closing axis, v across; centred) to a heightmap pixel
    (column, row), for cv2.warpAffine with WARP_INVERSE_MAP."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    a = np.array([[c, -s], [s, c]])
    centre = np.array([(shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0])
    b = centre - a @ np.array([(canvas - 1) / 2.0, (canvas - 1) / 2.0])
    return np.hstack([a, b[:, None]]).astype(np.float64)


def _shift_cols(img: np.ndarray, k: int) -> np.ndarray:
    """out[:, u] = img[:, u + k], zero where u + k falls outside."""
    out = np.zeros_like(img)
    if k >= 0:
        out[:, :img.shape[1] - k] = img[:, k:]
    else:
        out[:, -k:] = img[:, :img.shape[1] + k]
    return out


def _box_max(img: np.ndarray, half_rows: int, half_cols: int) -> np.ndarray:
    kernel = np.ones((2 * half_rows + 1, 2 * half_cols + 1), dtype=np.uint8)
    return cv2.dilate(img, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0.0)


def landing_heights(depth_hm: np.ndarray, resolution_m: float, g: GripperFootprint, bins: int) -> np.ndarray:
    """(bins, h, w) float32: for each closing angle k * pi / bins and pixel, the highest heightmap value under
    either open finger or under the hand less its height above the fingertips (m above the table)."""
    hm = np.ascontiguousarray(depth_hm, dtype=np.float32)
    h, w = hm.shape
    canvas = int(math.ceil(math.hypot(h, w))) + 2
    s0 = g.travel_m / resolution_m
    s1 = (g.travel_m + g.finger_outward_m) / resolution_m
    finger_mid = int(round((s0 + s1) / 2.0))
    finger_half = (int(round(s1 - s0)) + 1) // 2
    finger_across = int(round(g.finger_half_width_m / resolution_m))
    hand_along = int(round(g.hand_half_length_m / resolution_m))
    hand_across = int(round(g.hand_half_width_m / resolution_m))
    out = np.empty((bins, h, w), dtype=np.float32)
    flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    for k in range(bins):
        m = _rotation(k * math.pi / bins, (h, w), canvas)
        rot = cv2.warpAffine(hm, m, (canvas, canvas), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        fingers = _box_max(rot, finger_across, finger_half)
        worst = np.maximum(_shift_cols(fingers, finger_mid), _shift_cols(fingers, -finger_mid))
        np.maximum(worst, _box_max(rot, hand_across, hand_along) - g.hand_above_tips_m, out=worst)
        back = cv2.invertAffineTransform(m)
        out[k] = cv2.warpAffine(worst, back, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return out


def bin_angles(bins: int) -> np.ndarray:
    """The closing angles k pi / bins (radians, float32), k = 0 .. bins - 1."""
    return np.arange(bins, dtype=np.float32) * np.float32(math.pi / bins)


def angle_bin(angle_rad: np.ndarray, bins: int) -> np.ndarray:
    """The nearest of `bins` closing angles k * pi / bins (a closing axis and its reverse are one)."""
    return np.rint(np.mod(angle_rad, math.pi) / (math.pi / bins)).astype(np.int64) % bins


def clear_picks(depth_hm: np.ndarray, resolution_m: float, g: GripperFootprint, bins: int) -> np.ndarray:
    """bool (bins, h, w): a pick at that pixel along closing angle k * pi / bins gets its fingers down to the
    grasp height, and the pixel holds material at the pads' height (a pick centred over the floor closes on
    nothing)."""
    grasp = g.grasp_height(depth_hm)
    on_material = depth_hm >= grasp + max(PAD_HEIGHTS_M)
    return (landing_heights(depth_hm, resolution_m, g, bins) <= grasp + g.clear_m) & on_material


def nearest_clear_angle(angle_map: np.ndarray, clear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(valid bool (h, w), angles float32 (h, w)): where some closing angle is clear, and there the pixel's own
    angle when its bin is clear, else the clear bin's angle nearest to it (closing axes modulo pi)."""
    bins = clear.shape[0]
    own = np.asarray(angle_map, dtype=np.float32)
    centres = bin_angles(bins)[:, None, None]
    gap = np.abs(np.mod(own[None] - centres + np.float32(math.pi / 2), np.float32(math.pi)) - np.float32(math.pi / 2))
    gap = np.where(clear, gap, np.float32(np.inf))
    best = np.argmin(gap, axis=0)
    valid = clear.any(axis=0)
    rows, cols = np.indices(own.shape)
    keep = clear[angle_bin(own, bins), rows, cols]
    angles = np.where(keep | ~valid, own, best.astype(np.float32) * np.float32(math.pi / bins))
    return valid, angles.astype(np.float32, copy=False)


def _offsets(mask: np.ndarray, r0: int, c0: int, row: int, col: int) -> np.ndarray:
    rows, cols = np.nonzero(mask)
    return np.stack([cols + c0 - col, rows + r0 - row], axis=1).astype(np.float64)


def _material(depth_hm: np.ndarray, g: GripperFootprint, row: int, col: int, radius_px: int,
              sweep: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """(own, other): (n, 2) float64 (column, row) offsets from (row, col), within radius_px, of the material the
    finger pads squeeze (over the pick's grasp height, connected to the pick's pixel) and of the rest; None
    where the pick's pixel holds none at the pads' height. Material counts from the pads' top above the grasp
    height, or with `sweep` from their lowest contact (what the closing fingers meet first)."""
    h, w = depth_hm.shape
    r0, r1, c0, c1 = max(row - radius_px, 0), min(row + radius_px + 1, h), max(col - radius_px, 0), min(col + radius_px + 1, w)
    grasp = g.grasp_height(depth_hm[row, col])
    if depth_hm[row, col] < grasp + max(PAD_HEIGHTS_M):
        return None
    solid = depth_hm[r0:r1, c0:c1] >= grasp + (min(PAD_HEIGHTS_M) if sweep else max(PAD_HEIGHTS_M))
    _, labels = cv2.connectedComponents(solid.astype(np.uint8), connectivity=4)
    own = labels == labels[row - r0, col - c0]
    return _offsets(own, r0, c0, row, col), _offsets(solid & ~own, r0, c0, row, col)


def _pad_band(pts: np.ndarray, angle_rad: float, half_width_px: float) -> np.ndarray:
    """Positions along the closing axis (pixels) of the squeezed material's pixels (pts: (n, 2) column, row
    offsets) within the pads' half width of the closing line."""
    along = pts @ np.array([math.cos(angle_rad), math.sin(angle_rad)])
    return along[np.abs(pts @ np.array([-math.sin(angle_rad), math.cos(angle_rad)])) <= half_width_px]


def _squeezed(depth_hm: np.ndarray, resolution_m: float, g: GripperFootprint, row: int,
              col: int, sweep: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
    """_material within the fingers' reach of (row, col)."""
    radius = int(math.ceil(g.travel_m / resolution_m)) + 1
    return _material(np.asarray(depth_hm, dtype=np.float32), g, row, col, radius, sweep)


def closing_widths(depth_hm: np.ndarray, resolution_m: float, g: GripperFootprint, row: int, col: int,
                   angles_rad: np.ndarray, sweep: bool = False) -> np.ndarray:
    """How far apart the fingers close along each angle on a pick at (row, col): the extent along the closing
    axis of the squeezed material (_material) within the pads' width of the closing line (m); inf where
    it reaches an open finger (it does not fit) or the pick's pixel holds none. With `sweep` the material counts
    from the pads' lowest contact, and inf also where other material lies between the open fingers (a finger
    would push it into the grasp): of models/clutter's picks of novel objects, those failed 33 %, the rest 17 %
    (docs/journal.md, "What the closing fingers meet")."""
    reach = g.travel_m / resolution_m
    half = g.finger_half_width_m / resolution_m
    found = _squeezed(depth_hm, resolution_m, g, row, col, sweep)
    out = np.full(len(angles_rad), np.inf)
    if found is None:
        return out
    own, other = found
    for i, a in enumerate(angles_rad):
        along = _pad_band(own, float(a), half)
        if np.abs(along).max() >= reach:
            continue
        if sweep and (np.abs(_pad_band(other, float(a), half)) < reach).any():
            continue
        out[i] = (along.max() - along.min() + 1.0) * resolution_m
    return out


def surface_run_middle(depth_hm: np.ndarray, floor_m: float, row: int, col: int, direction_rad: float,
                       max_px: int, step_m: float = SURFACE_STEP_M) -> float:
    """Where the middle of the continuous surface through (row, col) lies along a direction (pixels from it,
    signed): walk both ways while each next pixel is above floor_m and within step_m of the last (a step
    taller than that is another object, or one lying against it), at most max_px each way."""
    h, w = depth_hm.shape
    dc, dr = math.cos(direction_rad), math.sin(direction_rad)
    ends = []
    for sign in (1.0, -1.0):
        last, reach = float(depth_hm[row, col]), 0
        for t in range(1, max_px + 1):
            r, c = int(round(row + sign * t * dr)), int(round(col + sign * t * dc))
            if not (0 <= r < h and 0 <= c < w):
                break
            z = float(depth_hm[r, c])
            if z < floor_m or abs(z - last) >= step_m:
                break
            last, reach = z, t
        ends.append(sign * reach)
    return (ends[0] + ends[1]) / 2.0


def centred_pixel(depth_hm: np.ndarray, resolution_m: float, g: GripperFootprint, clear: np.ndarray,
                  row: int, col: int, angle_rad: float, across: bool = False) -> tuple[int, int]:
    """(row, col) of a pick chosen at (row, col) along angle_rad moved along the closing axis to the middle of the
    material its pads squeeze, so both fingers meet it together instead of one shoving it into the other, and
    with `across` then across that axis to the middle of the surface under it (surface_run_middle: a tilted
    object grasped off its middle turns between the pads and slips out in the lift); the chosen pixel itself
    where nothing fits between the fingers or the moved pixel is not clear along that angle (clear: bool
    (bins, h, w))."""
    depth_hm = np.asarray(depth_hm, dtype=np.float32)
    found = _squeezed(depth_hm, resolution_m, g, row, col)
    if found is None:
        return row, col
    along = _pad_band(found[0], angle_rad, g.finger_half_width_m / resolution_m)
    if np.abs(along).max() >= g.travel_m / resolution_m:
        return row, col
    mid = (along.max() + along.min()) / 2.0
    r, c = row + int(round(mid * math.sin(angle_rad))), col + int(round(mid * math.cos(angle_rad)))
    if across and 0 <= r < depth_hm.shape[0] and 0 <= c < depth_hm.shape[1]:
        floor = g.grasp_height(depth_hm[row, col]) + max(PAD_HEIGHTS_M)
        across_dir = angle_rad + math.pi / 2
        shift = surface_run_middle(depth_hm, floor, r, c, across_dir, int(math.ceil(2 * g.travel_m / resolution_m)))
        r, c = r + int(round(shift * math.sin(across_dir))), c + int(round(shift * math.cos(across_dir)))
    k = int(angle_bin(np.float32(angle_rad), clear.shape[0]))
    inside = 0 <= r < clear.shape[1] and 0 <= c < clear.shape[2]
    return (r, c) if inside and clear[k, r, c] else (row, col)


def narrowest_clear_bin(depth_hm: np.ndarray, resolution_m: float, g: GripperFootprint, clear: np.ndarray,
                        row: int, col: int, own_angle: float, sweep: bool = False) -> int | None:
    """Of the clear closing angles at (row, col) (clear: bool (bins, h, w)), the one the fingers close narrowest
    along (closing_widths, with its `sweep`; of those within a pixel of it, the one nearest own_angle: a round
    object has no narrow side); None where no angle is clear or nothing fits between the fingers."""
    bins = clear.shape[0]
    candidates = np.flatnonzero(clear[:, row, col])
    widths = closing_widths(depth_hm, resolution_m, g, row, col, candidates * (math.pi / bins), sweep)
    if not np.isfinite(widths).any():
        return None
    near = candidates[widths <= widths.min() + resolution_m]
    gap = np.abs(np.mod(own_angle - near * (math.pi / bins) + math.pi / 2, math.pi) - math.pi / 2)
    return int(near[np.argmin(gap)])


@dataclass(frozen=True)
class PickClearance:
    """The decision's clearance rule: which pick pixels are valid on a heightmap (decide(..., clearance=))."""

    footprint: GripperFootprint
    resolution_m: float
    bins: int = DEFAULT_BINS
    narrowest: bool = False  # exploration.pick_angle == "narrowest": the chosen pick closes across its narrowest side
    centre: bool = False  # exploration.pick_centre: the chosen pick moves to the middle of what its pads squeeze
    across: bool = False  # exploration.pick_centre_across: ... and across the closing axis to the surface's middle
    sweep: bool = False  # exploration.pick_sweep: with narrowest, an angle whose closing fingers meet only the object

    @classmethod
    def for_config(cls, cfg: Config) -> PickClearance | None:
        """The rule of `exploration.pick_clearance` with the simulated hand (sim.finger_travel_m, pick depth and
        fingertip floor) on the workspace's heightmap, on the pick net's closing angles where it has a Q per
        angle (model.pick_angle_bins); None when it is off."""
        if not cfg.exploration.pick_clearance:
            return None
        sim = cfg.sim
        footprint = GripperFootprint(travel_m=sim.finger_travel_m, pick_depth_m=sim.pick_depth_m,
                                     tip_floor_m=sim.fingertip_clearance_m)
        return cls(footprint, cfg.workspace.resolution_m, cfg.model.pick_angle_bins or DEFAULT_BINS,
                   cfg.exploration.pick_angle == "narrowest", cfg.exploration.pick_centre,
                   cfg.exploration.pick_centre and cfg.exploration.pick_centre_across, cfg.exploration.pick_sweep)

    def clear(self, depth_hm: np.ndarray) -> np.ndarray:
        """bool (bins, h, w): clear_picks on this heightmap (it depends on the heightmap alone, so a decision
        computes it once however many times its nets run)."""
        return clear_picks(np.asarray(depth_hm, dtype=np.float32), self.resolution_m, self.footprint, self.bins)

    def closing_angle(self, depth_hm: np.ndarray, clear: np.ndarray, row: int, col: int, angle_rad: float) -> float:
        """The closing angle a pick at (row, col) chosen at angle_rad executes: with `narrowest`, the clear angle
        across which the squeezed material is narrowest (narrowest_clear_bin; with `sweep` first among the angles
        whose closing sweep meets nothing else: closing_widths), else (or where none fits) angle_rad."""
        if not self.narrowest:
            return angle_rad
        g, res = self.footprint, self.resolution_m
        k = narrowest_clear_bin(depth_hm, res, g, clear, row, col, angle_rad, sweep=True) if self.sweep else None
        if k is None:
            k = narrowest_clear_bin(depth_hm, res, g, clear, row, col, angle_rad)
        return angle_rad if k is None else k * math.pi / self.bins

    def executed(self, depth_hm: np.ndarray, clear: np.ndarray, row: int, col: int,
                 angle_rad: float) -> tuple[int, int, float]:
        """(row, col, angle) a pick chosen at (row, col, angle_rad) executes: closing_angle, then with `centre`
        the pixel moved to the middle of the squeezed material along that angle, and with `across` across it too
        (centred_pixel). The middle stays that of the pads' material with `sweep` too: centred on what the
        sweep also counts, picks of 30 blocks lost more objects in the lift (docs/journal.md)."""
        angle = self.closing_angle(depth_hm, clear, row, col, angle_rad)
        if self.centre:
            row, col = centred_pixel(depth_hm, self.resolution_m, self.footprint, clear, row, col, angle, self.across)
        return row, col, angle
