"""Behaviour-diversity tasks (sim/tasks.py): fixed starts, obstacles, descriptors, entropy."""

import numpy as np
import pytest

from sim.contract import pose_matrix, reward_and_success, transform_points
from sim.env import BinEnv
from sim.objects import load_objects
from sim.tasks import (
    ALIGN_OBSTACLE,
    TASKS,
    TaskStep,
    behaviour_entropy,
    push_align_behaviour,
    push_line_behaviour,
    yaw_quat,
)


def pose(x, y, yaw=0.0, z=0.03):
    return np.concatenate([[x, y, z], yaw_quat(yaw)])


def step(contact, motion, before, after=None, executed=True):
    after = before if after is None else after
    return TaskStep(np.asarray(contact, float), np.asarray(motion, float), executed, before, after)


def test_tasks_define_their_behaviours():
    assert TASKS["push-line"].n_behaviours == 24 and TASKS["push-align"].n_behaviours == 2
    assert len(TASKS["push-line"].behaviour_names) == 24


@pytest.mark.parametrize("name", list(TASKS))
def test_reset_gives_the_fixed_start_and_random_starts_for_training(name):
    task = TASKS[name]
    env = BinEnv(task=name, n_obj=32, n_bg=32)
    starts = []
    for seed in (0, 1):
        obs, info = env.reset(seed=seed)
        pos, quat = env.scene.object_pose()
        starts.append(pos)
        assert np.allclose(pos[:2], task.start[:2], atol=1e-3) and info["object"] == "cube"
        assert abs(quat[0]) > 0.9999  # yaw 0, upright
        assert not info["success"]
    np.testing.assert_allclose(starts[0], starts[1], atol=1e-9)  # the same pose whatever the seed
    env = BinEnv(task=name, task_start="random", n_obj=32, n_bg=32)
    xy = []
    for s in (0, 1):
        env.reset(seed=s)
        xy.append(env.scene.object_pose()[0][:2])
    xy = np.array(xy)
    (x0, x1), (y0, y1) = task.start_region
    assert not np.allclose(xy[0], xy[1])
    assert np.all(
        (xy[:, 0] > x0 - 0.01) & (xy[:, 0] < x1 + 0.01) & (xy[:, 1] > y0 - 0.01) & (xy[:, 1] < y1 + 0.01)
    )


def test_obstacle_collides_and_enters_the_background_cloud():
    env = BinEnv(task="push-align", n_obj=32, n_bg=512)
    obs, _ = env.reset(seed=0)
    assert env.scene.model.body("obstacle0").id > 0
    bg = obs["points"][32:]
    c, h = np.array(ALIGN_OBSTACLE.centre), np.array(ALIGN_OBSTACLE.half_size)
    on_box = np.all(np.abs(bg - c) <= h + 1e-4, axis=1)
    assert on_box.sum() > 20  # ~30% of the background samples lie on the box


def test_bad_task_arguments():
    with pytest.raises(ValueError, match="task"):
        BinEnv(task="push-sideways")
    with pytest.raises(ValueError, match="clutter"):
        BinEnv(task="push-line", clutter=1)


def test_push_line_success_means_across_the_line():
    cube = load_objects("cube")[0]
    goal = TASKS["push-line"].goal
    for y, success in ((-0.08, False), (-0.005, False), (0.005, True), (0.1, True)):
        pos, quat = np.array([0.05, y, 0.03]), yaw_quat(0.3)
        T = pose_matrix(pos, quat)
        reward, ok, dist = reward_and_success(
            transform_points(T, cube.surface_points), T, pose_matrix(*goal(pos, quat))
        )
        assert ok == success, y
        assert dist == pytest.approx(max(0.0, 0.03 - y), abs=1e-6)


def test_push_line_descriptor_face_and_sector():
    start = pose(0.0, -0.08)
    back = [0.0, -0.11, 0.02]  # on the -y face (face 3); its inward normal is +y
    assert push_line_behaviour([step(back, [0, 1, 0], start)]) == 6 * 3 + 0  # straight in
    assert push_line_behaviour([step(back, [-0.5, 0.5, 0], start)]) == 6 * 3 + 1  # 45 deg to the left
    assert push_line_behaviour([step(back, [0.5, 0.5, 0], start)]) == 6 * 3 + 5  # 45 deg to the right
    assert push_line_behaviour([step(back, [-1, 0, 0], start)]) == 6 * 3 + 2  # sideways (90 deg left)
    assert push_line_behaviour([step(back, [0, -1, 0], start)]) == 6 * 3 + 3  # straight away
    assert push_line_behaviour([step(back, [0, 0, -1], start)]) == 6 * 3 + 0  # no horizontal motion
    right = [0.03, -0.08, 0.02]  # the +x face (face 0), pushed in -x
    assert push_line_behaviour([step(right, [-1, 0, 0], start)]) == 0
    top = [0.01, -0.075, 0.06]  # top face, nearest side +x
    assert push_line_behaviour([step(top, [-1, 0, 0], start)]) == 0
    # faces are the cube's own: turned by 90 deg, the world -y side is the cube's -x face (face 2)
    turned = pose(0.0, -0.08, yaw=np.pi / 2)
    assert push_line_behaviour([step(back, [0, 1, 0], turned)]) == 6 * 2 + 0


def test_push_line_descriptor_uses_the_first_executed_primitive():
    start = pose(0.0, -0.08)
    refused = step([0.03, -0.08, 0.02], [-1, 0, 0], start, executed=False)
    pushed = step([0.0, -0.11, 0.02], [0, 1, 0], start, pose(0.0, -0.01))
    later = step([0.0, -0.04, 0.02], [1, 0, 0], pose(0.0, -0.01))
    assert push_line_behaviour([refused, pushed, later]) == 18
    assert push_line_behaviour([refused]) is None and push_line_behaviour([]) is None


def test_push_align_descriptor_upper_lower_none():
    def path(*xy):
        poses = [pose(x, y) for x, y in xy]
        return [step([0, 0, 0], [1, 0, 0], a, b) for a, b in zip(poses[:-1], poses[1:], strict=True)]

    assert push_align_behaviour(path((-0.1, 0.0), (-0.1, 0.09), (-0.02, 0.09), (0.06, 0.09), (0.1, 0))) == 0
    assert push_align_behaviour(path((-0.1, 0.0), (-0.1, -0.09), (0.06, -0.09), (0.1, 0))) == 1
    # interpolated at x = 0 between (-0.05, 0.1) and (0.05, -0.02): y = 0.04 > 0 -> upper
    assert push_align_behaviour(path((-0.1, 0.0), (-0.05, 0.1), (0.05, -0.02))) == 0
    assert push_align_behaviour(path((-0.1, 0.0), (-0.08, 0.05), (-0.05, 0.09))) is None  # never crosses
    assert push_align_behaviour([]) is None


def test_behaviour_entropy():
    assert behaviour_entropy(np.arange(24).repeat(3), 24) == pytest.approx(1.0)
    assert behaviour_entropy(np.full(50, 7), 24) == pytest.approx(0.0)
    assert behaviour_entropy([0, 0, 0, 1], 2) == pytest.approx(-(0.75 * np.log2(0.75) + 0.25 * np.log2(0.25)))
    assert behaviour_entropy([0, 1, -1, -1], 2) == pytest.approx(1.0)  # -1: no behaviour, left out
    assert behaviour_entropy([-1, -1], 2) == 0.0
    batch = np.array([[0, 1, 0, 1], [1, 1, 1, 1], [0, 0, 0, 1]])
    np.testing.assert_allclose(behaviour_entropy(batch, 2), [1.0, 0.0, 0.811278], atol=1e-6)
    with pytest.raises(ValueError):
        behaviour_entropy([0], 1)


def test_episodes_report_their_behaviour():
    from hydo_cli.rollout import baseline_policy, run_episodes

    env = BinEnv(task="push-line", n_obj=64, n_bg=64)
    results = run_episodes([env], baseline_policy("heuristic", 0), 2)
    assert [r.behaviour for r in results] == [18, 18]  # the heuristic pushes the -y face straight in
