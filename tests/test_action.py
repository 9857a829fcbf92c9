"""Action and the pixel <-> robot-frame conversion (VPG's convention)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from romannet.common.action import Action, pixel_to_position, position_to_pixel
from romannet.common.config import WorkspaceConfig

WS = WorkspaceConfig()


def test_vpg_convention():
    depth = np.zeros((224, 224), np.float32)
    depth[10, 20] = 0.05
    x, y, z = pixel_to_position(10, 20, depth, WS)
    assert x == pytest.approx(20 * 0.002 + WS.x_min_m)
    assert y == pytest.approx(10 * 0.002 + WS.y_min_m)
    assert z == pytest.approx(0.05 + WS.z_min_m)


@given(st.integers(0, 223), st.integers(0, 223), st.floats(0.0, 0.3))
def test_pixel_pose_round_trip(row, col, height_m):
    depth = np.full((224, 224), height_m, np.float32)
    x, y, z = pixel_to_position(row, col, depth, WS)
    assert position_to_pixel(x, y, WS) == (row, col)
    assert z == pytest.approx(height_m + WS.z_min_m, abs=1e-6)


def test_position_inside_a_pixel_maps_to_that_pixel():
    # A point anywhere inside pixel (5, 7)'s square belongs to it, as in the heightmap binning.
    x = WS.x_min_m + 7.9 * WS.resolution_m
    y = WS.y_min_m + 5.2 * WS.resolution_m
    assert position_to_pixel(x, y, WS) == (5, 7)
    assert position_to_pixel(WS.x_max_m - 1e-4, WS.y_max_m - 1e-4, WS) == (223, 223)


def test_outside_the_workspace_is_an_error():
    with pytest.raises(ValueError, match="outside the workspace"):
        position_to_pixel(WS.x_max_m + 0.01, 0.0, WS)
    with pytest.raises(ValueError, match="outside"):
        pixel_to_position(224, 0, np.zeros((224, 224), np.float32), WS)


def test_action_validates():
    with pytest.raises(ValueError, match="primitive"):
        Action("grasp", 0, 0, 0.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        Action("pick", 0, 0, float("nan"), 0.0)


def test_patch_max_takes_the_highest_point_around_the_pixel_clipped_at_the_edges():
    import numpy as np

    from romannet.common.action import patch_max

    hm = np.zeros((10, 10), dtype=np.float32)
    hm[0, 0], hm[5, 7], hm[9, 9] = 0.05, 0.02, 0.09
    assert patch_max(hm, 5, 5, 0.004, 0.002) == np.float32(0.02)  # radius 2 px reaches column 7
    assert patch_max(hm, 5, 5, 0.002, 0.002) == 0.0  # radius 1 px does not
    assert patch_max(hm, 1, 1, 0.002, 0.002) == np.float32(0.05)  # the window is clipped at the corner
    assert patch_max(hm, 9, 9, 0.0001, 0.002) == np.float32(0.09)  # at least one pixel around
