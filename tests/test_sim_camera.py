"""Simulator camera and the speed-ups that must not change what is simulated or seen.

- the table is composited from a pre-rendered layer: the image equals a render with the table drawn;
- the robot is culled from the render only when it cannot be seen: same image at home, drawn elsewhere;
- depth noise is reproducible under the seed and a cube still reads its height (median over its top);
- resting objects are put to sleep and still wake when the robot pushes them; the arm goes home directly
  only with an empty hand.
"""

from __future__ import annotations

import numpy as np
import pybullet as p
import pytest

from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.objects import ObjectSpec, spawn_object
from romannet.actor.sim.oracle import oracle_action
from romannet.actor.sim.robot import HOME_Q
from romannet.actor.sim.scene import TABLE_RGBA
from romannet.common.action import Action, position_to_pixel
from romannet.common.config import TaskConfig, WorkspaceConfig
from romannet.common.config_sim import SimConfig
from romannet.common.heightmap import zbuffer_to_depth

WS = WorkspaceConfig()
CUBE_XY = (0.55, 0.05)


def _env_with_cube(**sim_kwargs) -> SimEnv:
    """A stacking env reset to one 5 cm cube at CUBE_XY (and nothing else)."""
    sim = SimConfig(num_stacking_cubes=1, settle_steps=60, **sim_kwargs)
    env = SimEnv(task=TaskConfig(kind="stacking", goal_stack_height=5), sim=sim)
    env.reset(0)
    for body in list(env.scene.objects):
        env.scene.remove_object(body)
    body = spawn_object(env.scene.client, ObjectSpec("cube", (0.9, 0.1, 0.1, 1.0), (*CUBE_XY, 0.026)))
    env.scene.add_object(body)
    env.scene.settle(240)
    return env


@pytest.fixture(scope="module")
def env():
    e = _env_with_cube()
    yield e
    e.close()


def test_composited_table_gives_the_image_of_a_drawn_table(env):
    camera, c = env.scene.camera, env.scene.client
    frame = env.scene.render()
    p.changeVisualShape(env.scene.table_id, -1, rgbaColor=TABLE_RGBA, physicsClientId=c)
    try:
        rgb, zbuf = camera._raw()
    finally:
        p.changeVisualShape(env.scene.table_id, -1, rgbaColor=(0, 0, 0, 0), physicsClientId=c)
    differing = np.any(frame.color != rgb, axis=2).mean()
    assert differing < 1e-3  # at most a few z-fighting pixels where the cube meets the table
    cam = camera.cam
    reference = zbuffer_to_depth(zbuf, cam.near_m, cam.far_m)
    assert np.percentile(np.abs(frame.depth_m - reference), 99.9) < 1e-4


def test_robot_is_culled_only_when_out_of_view(env):
    arm = env.arm
    assert env.scene.camera.outside_view(arm.body_id)  # at home
    with_arm = env.scene.render()
    culled = env.scene.render(cull=(arm.body_id,))
    np.testing.assert_array_equal(with_arm.color, culled.color)
    np.testing.assert_array_equal(with_arm.depth_m, culled.depth_m)
    # Over the workspace the arm is seen, and drawn.
    q, err = arm._ik(np.array([0.5, -0.05, 0.2]), 0.0, arm.joint_positions())
    assert err < 0.01
    for j, qj in enumerate(q):
        p.resetJointState(arm.body_id, j, qj, physicsClientId=env.scene.client)
    try:
        assert not env.scene.camera.outside_view(arm.body_id)
        seen = env.scene.render(cull=(arm.body_id,))
        assert np.any(seen.color != with_arm.color, axis=2).mean() > 0.01
    finally:
        arm.reset()
    # The colours come back after a culled render.
    np.testing.assert_array_equal(env.scene.render(cull=(arm.body_id,)).color, with_arm.color)


def test_depth_noise_is_reproducible_and_the_cube_still_reads_5cm():
    std = 0.002
    frames = []
    for _ in range(2):
        with _env_with_cube(depth_noise_std_m=std) as noisy:
            noisy.rng = np.random.default_rng(123)
            frames.append(noisy.scene.render(noisy.rng, cull=(noisy.arm.body_id,)))
            _, depth_hm = noisy.scene.heightmaps(frames[-1])
    np.testing.assert_array_equal(frames[0].depth_m, frames[1].depth_m)
    with _env_with_cube() as exact:
        reference = exact.scene.render().depth_m
    residual = frames[0].depth_m - reference
    assert abs(float(residual.std()) - std) < 0.1 * std and abs(float(residual.mean())) < 1e-4
    row, col = position_to_pixel(*CUBE_XY, WS)
    top = depth_hm[row - 8:row + 9, col - 8:col + 9]
    # Each heightmap pixel keeps the highest of its ~3 camera points, so noise biases it up by ~std.
    assert abs(float(np.median(top)) - 0.050) <= 0.003 + std


def test_resting_objects_sleep_and_a_push_still_moves_them(env):
    cube = env.scene.objects[0]
    env.scene.settle(60)  # at rest: ends by putting every object to sleep
    env.obs = env._observe()
    row, col = position_to_pixel(CUBE_XY[0] - 0.06, CUBE_XY[1], WS)
    start = env.scene.pose(cube)[0]
    result = env.step(Action("push", row, col, 0.0, 1.0))
    assert result.success and env.scene.pose(cube)[0][0] - start[0] > 0.02
    np.testing.assert_allclose(env.arm.joint_positions(), HOME_Q, atol=0.01)  # back home


def test_a_held_cube_goes_home_with_the_arm():
    with _env_with_cube() as e:
        e.obs = e._observe()
        result = e.step(oracle_action(e))
        assert result.success and e.holding
        assert e.prims.held_body() == e.held_body
        assert e.scene.camera.outside_view(e.arm.body_id)
