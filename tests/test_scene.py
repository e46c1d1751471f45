"""Scene, stable poses and primitive geometry."""

import mujoco
import numpy as np
import pytest

from sim.goals import STABLE_MAX_MOVE_M, STABLE_MAX_TURN_RAD, quat_angle, sample_placement, stable_poses
from sim.objects import builtin_objects, extra_train_objects, load_objects, varied_train_objects
from sim.primitive import (
    FLOOR_CLEARANCE_M,
    N_WAYPOINTS,
    SIM_WORKSPACE,
    PrimitiveRejected,
    check_plan,
    primitive_waypoints,
)
from sim.scene import BinScene


def test_scene_compiles_and_steps_without_warnings():
    scene = BinScene(load_objects("mug_00")[0])
    rng = np.random.default_rng(0)
    lo, hi = scene.model.actuator_ctrlrange.T
    for _ in range(200):  # 1 s of quasi-random controls spanning ctrlrange (Menagerie's model test)
        scene.data.ctrl[:] = rng.uniform(lo, hi)
        mujoco.mj_step(scene.model, scene.data)
    assert all(w.number == 0 for w in scene.data.warning), [w.number for w in scene.data.warning]


def test_model_counts_are_deliberate():
    scene = BinScene(load_objects("cube")[0])
    m = scene.model
    assert (m.nq, m.nv, m.nu) == (3 + 7, 3 + 6, 3)
    assert m.opt.timestep == pytest.approx(0.005)


def test_every_builtin_stable_pose_stays_put():
    """A placed object moves < 5 mm and < 3 degrees over 1 s, for every built-in, train-extra and
    train-varied object
    (their poses are shipped: nothing is computed here, or at training time)."""
    rng = np.random.default_rng(0)
    worst = (0.0, 0.0, "")
    for asset in builtin_objects() + extra_train_objects() + varied_train_objects():
        poses = stable_poses(asset)
        assert poses.shape == (100, 5)
        scene = BinScene(asset)
        for k in rng.choice(len(poses), 3, replace=False):
            pos, quat = sample_placement(asset, poses[k], rng)
            scene.set_object_pose(pos, quat)
            mujoco.mj_step(scene.model, scene.data, nstep=200)
            p1, q1 = scene.object_pose()
            move, turn = np.linalg.norm(p1 - pos), quat_angle(quat, q1)
            if move > worst[0]:
                worst = (move, turn, asset.name)
            assert move < STABLE_MAX_MOVE_M, (asset.name, k, move)
            assert turn < STABLE_MAX_TURN_RAD, (asset.name, k, np.rad2deg(turn))


def test_hacman_contacts_take_hacmans_settings_and_hydo_keeps_its_own():
    """``contacts="hacman"`` (sim.scene) sets HACMan's bin env's contact settings on the same scene;
    the default changes nothing."""
    from sim.scene import (
        HACMAN_FINGER_FRICTION,
        HACMAN_OBJECT_DENSITY,
        HACMAN_OBJECT_FRICTION,
        OBJECT_DENSITY,
    )

    asset = load_objects("mug_00")[0]
    own, hac = BinScene(asset).model, BinScene(asset, contacts="hacman").model
    for m, cone, noslip in (
        (own, mujoco.mjtCone.mjCONE_PYRAMIDAL, 0),
        (hac, mujoco.mjtCone.mjCONE_ELLIPTIC, 20),
    ):
        assert m.opt.cone == cone and m.opt.noslip_iterations == noslip
        assert m.opt.timestep == pytest.approx(0.005)  # the step is hydo's in both
    assert own.opt.impratio == 1.0 and hac.opt.impratio == 20.0
    np.testing.assert_allclose(own.geom("hand_fingers").friction, [0.8, 0.005, 0.0001])
    np.testing.assert_allclose(hac.geom("hand_fingers").friction, HACMAN_FINGER_FRICTION)
    assert own.geom("hand_palm").contype == 1 and hac.geom("hand_palm").contype == 0
    assert hac.geom("hand_palm").conaffinity == 0
    for m, friction, condim in ((own, [0.5, 0.005, 0.0001], 3), (hac, HACMAN_OBJECT_FRICTION, 4)):
        np.testing.assert_allclose(m.geom("object_geom0").friction, friction)
        assert m.geom("object_geom0").condim == condim
        # the bin wins object-bin contacts in HACMan's (priority 1): their friction stays the bin's 0.5
        assert m.geom("bin_floor").priority == (m is hac) and m.geom("bin_floor").condim == condim
        np.testing.assert_allclose(m.geom("bin_floor").friction, [0.5, 0.005, 0.0001])
    # the same shape at 50 kg/m^3 instead of 400; the goal ghost has no mass in either
    ratio = hac.body("object").mass[0] / own.body("object").mass[0]
    assert ratio == pytest.approx(HACMAN_OBJECT_DENSITY / OBJECT_DENSITY, rel=1e-6)
    with pytest.raises(ValueError, match="contacts"):
        BinScene(asset, contacts="robosuite")


def test_primitive_waypoints_geometry():
    p, n, m = np.array([0.0, 0.0, 0.03]), np.array([-1.0, 0, 0]), np.array([1.0, 0.5, -1.0])
    w = primitive_waypoints(p, n, m)
    assert w.shape == (N_WAYPOINTS, 3)
    np.testing.assert_allclose(w[0], [-0.04, 0, 0.03])
    np.testing.assert_allclose(w[1], [-0.02, 0, 0.03])
    np.testing.assert_allclose(w[2], p)
    np.testing.assert_allclose(w[3][:2], [0.03, 0.015])
    # the downward push is clamped to 5 mm above the floor, never below
    assert np.all(w[:, 2] >= FLOOR_CLEARANCE_M - 1e-12)
    assert w[5][2] == pytest.approx(FLOOR_CLEARANCE_M)
    assert w[6][2] == pytest.approx(w[5][2] + 0.06)


def test_plan_outside_workspace_is_refused_not_clipped():
    w = primitive_waypoints(np.array([0.2, 0, 0.03]), np.array([1.0, 0, 0]), np.zeros(3))
    with pytest.raises(PrimitiveRejected, match=r"waypoint 0 x=0\.240 m is above the workspace bound"):
        check_plan(w, SIM_WORKSPACE)
    bad = w.copy()
    bad[3, 1] = np.nan
    with pytest.raises(PrimitiveRejected, match="NaN"):
        check_plan(bad)
    check_plan(primitive_waypoints(np.zeros(3) + [0, 0, 0.03], np.array([0, 1.0, 0]), np.ones(3) * 0.5))


def test_primitive_pushes_the_object():
    asset = load_objects("cube")[0]
    scene = BinScene(asset)
    scene.set_object_pose(np.array([0.0, 0.0, 0.03]), np.array([1.0, 0, 0, 0]))
    # contact on the -x face at mid height, push +x by 9 cm
    w = primitive_waypoints(np.array([-0.03, 0.0, 0.03]), np.array([-1.0, 0, 0]), np.array([1.0, 0, 0]))
    check_plan(w)
    result = scene.execute_primitive(w)
    assert result.executed
    pos, _ = scene.object_pose()
    assert 0.07 < pos[0] < 0.12, pos  # 9 cm push plus a little sliding after it
    assert abs(pos[1]) < 0.01
    assert scene.object_speed()[0] < 0.01  # settled


def test_primitive_rollout_is_the_python_stepping_loop_bit_for_bit():
    """The primitive's open loop runs in one mujoco.rollout call; it must be the same mj_step calls
    as setting ctrl and stepping in Python (the loop it replaced), to the last bit of the full
    integration state (mocap poses and warm start included)."""
    from sim.scene import push_controls

    scene = BinScene(load_objects("box_00")[0])
    scene.set_object_pose(np.array([0.0, 0.0, 0.03]), np.array([1.0, 0, 0, 0]))
    scene.set_goal_ghost(np.array([0.1, 0.05, 0.03]), np.array([0.0, 0, 0, 1.0]))
    scene.settle()
    w = primitive_waypoints(np.array([-0.04, 0.0, 0.02]), np.array([-1.0, 0, 0]), np.array([0.8, 0.3, 0]))
    controls = push_controls(w, scene.model.opt.timestep)
    # the targets: straight lines, each push's end held for TRACK_STEPS, ending at the lift
    assert np.array_equal(controls[-1], w[-1]) and len(controls) > 100
    m, d = scene.model, scene.data
    d.qpos[scene.hand_qadr] = w[0]
    d.ctrl[:] = w[0]
    mujoco.mj_forward(m, d)
    start = scene.get_state()
    for row in controls:
        d.ctrl[:] = row
        mujoco.mj_step(m, d)
    want = scene.get_state()
    scene.set_state(start)
    scene._run_controls(controls)
    assert np.array_equal(scene.get_state(), want)
    assert np.abs(scene.object_pose()[0] - start[1 + scene.obj_qadr : 4 + scene.obj_qadr]).max() > 0.01


def _press_down_on(scene: BinScene) -> np.ndarray:
    """Waypoints of a push straight down onto the top of a cube resting at the bin centre: the object
    cannot give way, so the hand's force climbs to its actuator limit (60 N vertically)."""
    scene.set_object_pose(np.array([0.0, 0.0, 0.03]), np.array([1.0, 0, 0, 0]))
    scene.settle()
    w = primitive_waypoints(np.array([0.0, 0.0, 0.06]), np.array([0.0, 0, 1.0]), np.array([0.0, 0, -1.0]))
    check_plan(w)
    return w


def test_hand_contact_sensor_is_the_net_contact_force_on_the_hand():
    """The sensor the force stop reads: the norm of the summed contact forces on the hand's geoms,
    as mj_contactForce gives them (what robot.twin's arm measures)."""
    from sim.scene import push_controls

    scene = BinScene(load_objects("cube")[0])
    w = _press_down_on(scene)
    m, d = scene.model, scene.data
    d.qpos[scene.hand_qadr] = w[0]
    d.ctrl[:] = w[0]
    mujoco.mj_forward(m, d)
    checked = 0
    for row in push_controls(w, m.opt.timestep)[:150]:
        d.ctrl[:] = row
        mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)  # sensors and contacts of the same state
        total, f6 = np.zeros(3), np.zeros(6)
        for i in range(d.ncon):
            g = d.contact.geom[i]
            on1, on2 = scene._is_hand_geom[g[0]], scene._is_hand_geom[g[1]]
            if on1 == on2:
                continue
            mujoco.mj_contactForce(m, d, i, f6)
            f = d.contact.frame[i].reshape(3, 3).T @ f6[:3]
            total += f if on2 else -f
        sensed = np.linalg.norm(d.sensordata[scene._hand_force])
        assert sensed == pytest.approx(np.linalg.norm(total), rel=1e-6, abs=1e-9)
        checked += sensed > 1.0
    assert checked > 10  # the hand pressed on the cube for a good part of it


def test_force_stop_ends_a_push_the_arm_would_stop():
    """Pressing a cube into the floor passes 30 N: with the stop the primitive ends there and the
    hand lets go; without it the same push runs to the end (the hand before the stop)."""
    from sim.primitive import FORCE_STOP_N

    stopped = BinScene(load_objects("cube")[0])
    result = stopped.execute_primitive(_press_down_on(stopped))
    assert result.executed and result.force_stopped
    unstopped = BinScene(load_objects("cube")[0], force_stop_n=None)
    full = unstopped.execute_primitive(_press_down_on(unstopped))
    assert full.executed and not full.force_stopped
    assert result.physics_steps < full.physics_steps
    assert stopped.force_stop_n == FORCE_STOP_N == 30.0
    # a push that only slides the cube stays under the stop
    free = BinScene(load_objects("cube")[0])
    free.set_object_pose(np.array([0.0, 0.0, 0.03]), np.array([1.0, 0, 0, 0]))
    w = primitive_waypoints(np.array([-0.03, 0.0, 0.03]), np.array([-1.0, 0, 0]), np.array([1.0, 0, 0]))
    assert not free.execute_primitive(w).force_stopped
