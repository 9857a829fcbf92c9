"""Why a simulated pick failed, from the simulator's ground truth once the fingers have closed.

A failed pick reads "nothing_grasped" on a robot; the simulator can say more. Right after the fingers close
(before the lift): which object both fingers touch, how far its centre of mass lies from the closing line
(across it: the lever the object turns about the fingers with) and along it, and how far it is tilted. After
the lift the failure's cause is one of CAUSES. SimEnv puts these in every pick's step info (recorded with
each episode), and `romannet eval` counts failed picks by cause.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as p

# Why a pick that reached its grasp height failed: the fingers closed to (almost) nothing; they closed on
# different objects (or one finger on none); both held one object, which was lost on the way up.
CAUSES = ("closed_on_nothing", "fingers_on_two_objects", "lost_in_lift")


@dataclass(frozen=True)
class ClosedGrasp:
    """The grasp as the fingers have closed: gap_m between the pads; body, the one object both fingers
    touch (None if none), with its tilt and its centre of mass's offset from the pick's point along and
    across the closing axis (m; NaN without a body)."""

    gap_m: float
    body: int | None = None
    tilt_deg: float = math.nan
    offset_along_m: float = math.nan
    offset_across_m: float = math.nan

    def cause(self, held: bool, min_gap_m: float) -> str:
        """"held", or the failure's cause (one of CAUSES)."""
        if held:
            return "held"
        if self.gap_m <= min_gap_m:
            return "closed_on_nothing"
        return "fingers_on_two_objects" if self.body is None else "lost_in_lift"

    def info(self, held: bool, min_gap_m: float) -> dict[str, float | str]:
        """The step info's fields: grasp (held or the cause) and, with a body, its tilt and offsets."""
        out: dict[str, float | str] = {"grasp": self.cause(held, min_gap_m)}
        if self.body is not None:
            out.update(grasp_tilt_deg=round(self.tilt_deg, 2), grasp_offset_along_m=round(self.offset_along_m, 4),
                       grasp_offset_across_m=round(self.offset_across_m, 4))
        return out


def tilt_deg(orientation_xyzw: tuple[float, float, float, float]) -> float:
    """How far a body's nearest own axis is from the vertical (degrees, 0..54.7): 0 lying on any face."""
    rot = np.array(p.getMatrixFromQuaternion(orientation_xyzw)).reshape(3, 3)
    return math.degrees(math.acos(min(1.0, float(np.abs(rot[2]).max()))))


def closed_grasp(client: int, hand_body: int, fingers: tuple[int, int], objects: list[int], gap_m: float,
                 xy_m: tuple[float, float], angle_rad: float) -> ClosedGrasp:
    """The ClosedGrasp of a hand whose fingers (link indices) have closed to gap_m over the point xy_m along
    the closing axis angle_rad."""
    touched = [{c[2] for c in p.getContactPoints(hand_body, linkIndexA=f, physicsClientId=client)} & set(objects)
               for f in fingers]
    both = sorted(touched[0] & touched[1])
    if not both:
        return ClosedGrasp(gap_m)
    body = both[0]
    pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=client)
    local_com = p.getDynamicsInfo(body, -1, physicsClientId=client)[3]
    rot = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
    com = np.asarray(pos) + rot @ np.asarray(local_com)
    off = com[:2] - np.asarray(xy_m)
    d = np.array([math.cos(angle_rad), math.sin(angle_rad)])
    return ClosedGrasp(gap_m, body, tilt_deg(orn), float(off @ d), float(off @ np.array([-d[1], d[0]])))
