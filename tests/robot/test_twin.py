"""The MuJoCo twin: the arm pushes, the contact-force stop fires on a welded object, IK refuses
unreachable plans, rendered perception matches ground truth, and ``hydo deploy --robot sim`` runs end
to end without torch."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from robot.cameras import CameraSet
from robot.connect import open_cameras
from robot.errors import UnreachableError
from robot.executor import Outcome
from robot.perception import capture_background, segment
from robot.safety import SafetyGate
from robot.session_log import SessionLog, read_log
from robot.twin import TwinExecutor, TwinWorld, sample_episode
from sim.depth import mask_iou
from sim.objects import load_objects


@pytest.fixture(scope="module")
def world(cell):
    w = TwinWorld(cell, seed=0)
    w.load(load_objects("cube")[0])
    yield w
    w.close()


def place_cube(world, cell, xy=(0.54, 0.0)):
    world.reset_arm()
    world.weld_object(False)
    world.place_object(np.array([xy[0], xy[1], cell.floor_z + 0.03]), [1.0, 0, 0, 0])


def test_arm_starts_at_home_out_of_view_of_the_bin(world, cell):
    p = world.fingertip()
    assert p[2] > cell.approach_z and np.allclose(world.joints(), cell.home_joints)
    for i in range(len(cell.cameras)):  # only the arm's fixed base is seen (behind the bin)
        arm = world.true_mask(i, "arm")
        assert arm.sum() < 0.03 * arm.size


def test_twin_push_moves_the_object_and_logs_every_command(world, cell, tmp_path):
    place_cube(world, cell)
    before = world.object_pose()[0]
    gate = SafetyGate(cell, world.kin)
    plan = gate.plan_primitive(before + [0.03, 0.0, 0.0], np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]))
    with SessionLog(tmp_path / "s") as log, TwinExecutor(world, cell, log=log) as robot:
        result = robot.execute(plan)
    assert result.outcome is Outcome.ok and len(result.commanded) == len(plan.commands)
    moved = world.object_pose()[0] - before
    assert -0.12 < moved[0] < -0.05 and abs(moved[1]) < 0.02  # pushed ~9 cm (3 x 3 cm) towards the robot
    assert robot.at_home()
    lines = read_log(tmp_path / "s")
    kinds = [e["event"] for e in lines]
    assert kinds.count("command") == len(plan.commands)
    for i, e in enumerate(lines):  # every command_done follows its command line
        if e["event"] == "command_done":
            assert lines[i - 1]["event"] == "command" and lines[i - 1]["index"] == e["index"]


def test_contact_force_stop_on_a_welded_object(world, cell, tmp_path):
    place_cube(world, cell)
    world.weld_object(True)
    try:
        p0 = world.object_pose()[0]
        gate = SafetyGate(cell, world.kin)
        plan = gate.plan_primitive(p0 + [0.03, 0.0, 0.0], np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]))
        with SessionLog(tmp_path / "s") as log, TwinExecutor(world, cell, log=log) as robot:
            result = robot.execute(plan)
            assert result.outcome is Outcome.reaction_fired
            assert result.failed.kind == "push" and "w5 push 3" not in [
                c.label for c in result.commanded[:-1]
            ]
            assert cell.limits.force_stop < result.peak_force <= 1.2 * cell.limits.force_stop
            retract = gate.plan_retract(robot.fingertip(), robot.joints())
            assert robot.execute(retract).outcome is Outcome.ok and robot.at_home()
        np.testing.assert_allclose(world.object_pose()[0], p0, atol=2e-3)
        done = [e for e in read_log(tmp_path / "s") if e["event"] == "command_done"]
        assert any(e["outcome"] == "reaction_fired" for e in done)
    finally:
        world.weld_object(False)


def test_twin_tracks_free_space_moves_to_2_mm(world, cell):
    """The twin's controller, like libfranka's torque interface, has the arm's joint friction
    compensated: free moves end on their targets (with dm-robotics-panda's uncompensated joint
    friction they stopped 2-7 mm short, so the fingertip did not follow the primitive's waypoints)."""
    place_cube(world, cell)
    gate = SafetyGate(cell, world.kin)
    plan = gate.plan_primitive(np.array([0.39, -0.15, 0.05]), np.array([0, 0, 1.0]), np.zeros(3))
    robot = TwinExecutor(world, cell)
    with robot:
        errors = [np.linalg.norm(robot.send(c).position - c.target) for c in plan.commands]
    assert max(errors) < 0.0025, np.round(np.array(errors) * 1000, 1)


def test_palm_on_the_bin_rim_reflex_then_checked_retract(world, cell, tmp_path):
    """A push 2 cm from the bin wall 6 cm above the floor puts the 20 cm wide palm (as in training's
    hand) onto the wall's rim: the twin's reflex fires. The arm then stops and holds, so after one
    recovery the checked retract leaves the rim without a new stop (before, it started inside the
    impact's transient and stopped again)."""
    place_cube(world, cell)
    gate = SafetyGate(cell, world.kin)
    plan = gate.plan_primitive(np.array([0.44, -0.20, 0.06]), np.array([0, 0, 1.0]), np.zeros(3))
    with SessionLog(tmp_path / "s") as log, TwinExecutor(world, cell, log=log) as robot:
        result = robot.execute(plan)
        assert result.outcome is Outcome.reflex and result.failed.label in ("w1 approach", "w2 contact")
        assert robot.robot_mode().value == "reflex"
        robot.recover()
        retract = robot.execute(gate.plan_retract(robot.fingertip(), robot.joints()))
        assert retract.outcome is Outcome.ok and retract.peak_force < cell.limits.force_stop
        assert robot.at_home()


def test_twin_reflex_limit_ends_the_episode_a_real_arm_stops_the_run(tiny_model, tmp_path, monkeypatch):
    """robot-safety.md 13: at most three recoveries per episode, so the fourth reflex stops the run on
    a real arm (tests/robot/test_faults.py) and in the twin with ``--on-refusal stop``; the twin's
    evaluation (default) ends that episode instead, counts it, and goes on with the next one."""
    from robot.errors import RecoveryLimitError
    from robot.executor import MoveResult, RobotMode
    from robot.loop import DeployConfig, Deployment

    def scripted_reflex(self, command):  # every contact move ends in a reflex, as on the bin rim
        if command.kind == "contact":
            w = self.world
            w.mode, w.errors = RobotMode.reflex, ("cartesian_reflex",)
            return MoveResult(Outcome.reflex, w.fingertip(), 45.0, w.errors, "scripted reflex")
        return original(self, command)

    original = TwinExecutor._move
    monkeypatch.setattr(TwinExecutor, "_move", scripted_reflex)

    def deployment(name, **cfg):
        dep = Deployment.prepare(
            DeployConfig(
                robot="sim", model=tiny_model, episodes=2, max_steps=4, log_dir=tmp_path / name, **cfg
            )
        )

        def act(points, features, rng, normals=None, feasible=None):  # the highest object point, no push
            return int(np.argmax(points[: dep.policy.n_obj, 2])), np.zeros(3, np.float32), {}

        dep.policy.act = act
        return dep

    with pytest.raises(RecoveryLimitError, match="reflex number 4 in this episode"):
        deployment("stop", on_refusal="stop").run()
    res = deployment("evaluate").run()
    assert [e.reason.startswith("reflex limit: reflex number 4") for e in res.episodes] == [True, True]
    s = res.summary()
    assert s["reflexes"] == 8 and s["reflex_limit_episodes"] == 2
    lines = read_log(tmp_path / "evaluate")
    assert [e["episode"] for e in lines if e["event"] == "episode_stopped"] == [0, 1]
    assert len([e for e in lines if e["event"] == "recovery"]) == 6  # three per episode, then no more


@pytest.mark.parametrize("goals", ["planar", "6d"])
def test_twin_episodes_are_the_training_envs_in_the_cells_bin(world, cell, goals):
    """One home for episode sampling (sim.goals): for the same seed the twin draws the training env's
    object, start and goal, moved to the cell's bin."""
    import sim  # noqa: F401
    from sim.env import BinEnv

    assets = load_objects("train")
    asset, start, goal = sample_episode(world, assets, goals, np.random.default_rng(11))
    env = BinEnv(objects=assets, goals=goals)
    _, info = env.reset(seed=11)  # gymnasium seeds PCG64 like np.random.default_rng
    assert info["object"] == asset.name
    np.testing.assert_allclose(goal[0] - cell.bin_center, env.goal_pose[0], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(goal[1], env.goal_pose[1])
    env.close()


def test_a_bin_where_joint_4_hits_its_limit_is_refused_at_load_and_its_plans_by_the_gate(tmp_path):
    """The example cell's bin sat 0.50 m in front of the base, where a push at the middle of the near
    wall folds the arm onto joint 4's limit: the twin refused such plans mid-episode. The cell check
    now covers a grid of the workspace and refuses that bin at load; loaded anyway (``reach=False``),
    the gate still refuses the plan, so nothing moves."""
    import copy

    import yaml

    from robot.arm import ArmKinematics
    from robot.cell import EXAMPLE_CELL, CellError, load_cell

    data = copy.deepcopy(yaml.safe_load(EXAMPLE_CELL.read_text()))
    data["bin"]["center_m"][0] = 0.50
    data["workspace"]["low_m"][0], data["workspace"]["high_m"][0] = 0.287, 0.713
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(CellError, match="needs joint 4 within 0.0\\d+ rad of its limit"):
        load_cell(path)
    old = load_cell(path, reach=False)
    gate = SafetyGate(old, ArmKinematics.for_cell(old))
    with pytest.raises(UnreachableError, match="joint 4 within 0.0\\d+ rad of its limit"):
        gate.plan_primitive(np.array([0.30, 0.0, 0.10]), np.array([0, 0, 1.0]), np.zeros(3))


def test_rendered_segmentation_and_registration_match_the_twin(world, cell):
    from robot.registration import adds_error, register
    from sim.contract import transform_points

    rng = np.random.default_rng(0)
    world.reset_arm()
    world.hide_object()
    with open_cameras(cell, "sim", world=world) as cams:
        bg = capture_background(cams, cell, 3)
        T_goal = world.place_object([0.55, 0.05, cell.floor_z + 0.03], [1.0, 0, 0, 0])
        goal = segment(cams.capture(), bg, cell, rng)
        world.place_object([0.46, -0.06, cell.floor_z + 0.03], [np.cos(0.3), 0, 0, np.sin(0.3)])
        seg = segment(cams.capture(), bg, cell, rng)
    true = np.stack([world.true_mask(i) for i in range(3)])
    assert mask_iou(np.stack(seg.masks), true) > 0.85
    reg = register(seg.obj_points, goal.obj_points, "planar")
    T_true = T_goal @ np.linalg.inv(world.object_T())
    surf = transform_points(world.object_T(), world.asset.surface_points)
    assert adds_error(reg.T, T_true, surf) < 0.004 and reg.rmse < cell.perception.registration_max_rmse


NO_TORCH = textwrap.dedent(
    """
    import sys, importlib.abc
    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name == "torch" or name.startswith("torch."):
                raise ImportError("torch is blocked: deploy must not need it")
    sys.meta_path.insert(0, Block())
    from hydo_cli.main import main
    try:
        main()
    finally:
        assert "torch" not in sys.modules
    """
)


def hydo_no_torch(*args, timeout=600):
    return subprocess.run(
        [sys.executable, "-c", NO_TORCH, *args], capture_output=True, text=True, timeout=timeout
    )


def test_deploy_sim_end_to_end_without_torch(tiny_model, tmp_path):
    """``hydo deploy --robot sim --model <tiny export> --episodes 2``: rendered cameras, perception,
    registration, ONNX policy, safety gate, the twin arm; then the replay camera plays it back."""
    session = tmp_path / "session"
    r = hydo_no_torch(
        "deploy",
        "--robot",
        "sim",
        "--model",
        str(tiny_model),
        "--episodes",
        "2",
        "--max-steps",
        "1",
        "--log",
        str(session),
    )
    assert r.returncode == 0, r.stderr
    assert "success rate" in r.stdout and "segmentation IoU" in r.stdout
    summary = json.loads((session / "summary.json").read_text())
    assert summary["episodes"] == 2
    assert summary["mean_iou"] > 0.8 and summary["mean_registration_error_m"] < 0.01
    lines = read_log(session)
    ends = [e for e in lines if e["event"] == "episode_end"]
    assert len(ends) == 2 and all(e["true_distance"] is not None for e in ends)
    outcomes = [e for e in lines if e["event"] in ("outcome", "refused")]
    assert outcomes, "each episode either executed or refused its primitive"
    commands = [e for e in lines if e["event"] == "command"]
    assert summary["commands_sent"] == len(commands)
    assert (session / "background.npz").exists() and (session / "goals" / "e000.npz").exists()

    # Replay: the recorded frames through perception and the policy again, moving nothing.
    r2 = hydo_no_torch(
        "deploy", "--replay", str(session), "--model", str(tiny_model), "--log", str(tmp_path / "replay")
    )
    assert r2.returncode == 0, r2.stderr
    assert (
        "dry run" in r2.stderr
        and json.loads((tmp_path / "replay" / "summary.json").read_text())["commands_sent"] == 0
    )


def test_capture_background_and_goal_in_the_twin(tmp_path):
    bg, goal = tmp_path / "background.npz", tmp_path / "goal.npz"
    r = hydo_no_torch("deploy", "capture-background", "--robot", "sim", "--out", str(bg), "--frames", "2")
    assert r.returncode == 0 and bg.exists(), r.stderr
    r = hydo_no_torch(
        "deploy",
        "capture-goal",
        "--robot",
        "sim",
        "--background",
        str(bg),
        "--out",
        str(goal),
        "--offset",
        "0.1,0,30",
    )
    assert r.returncode == 0 and "goal cloud of" in r.stderr, r.stderr
    from robot.registration import Goal

    g = Goal.load(goal)
    assert g.kind == "offset" and g.offset == (0.1, 0.0, 30.0) and len(g.points) > 100


def test_twin_cameras_close_and_reopen(world, cell):
    cams = open_cameras(cell, "sim", world=world)
    assert isinstance(cams, CameraSet)
    for round_ in (1, 2):  # the second round reopens the same, closed cameras
        with cams:
            assert all(cam._open for cam in cams)
            frames = cams.capture()
        assert not any(cam._open for cam in cams)
        assert [f.serial for f in frames] == [c.serial for c in cell.cameras]
        assert [f.index for f in frames] == [round_] * len(frames)  # the same cameras, counting on
        assert all(np.isfinite(f.depth).all() and (f.depth > 0).mean() > 0.5 for f in frames)
