"""The robot libraries: the FR3 executor on a fake franky (absolute base-frame targets, a force
reaction that returns normally is still reported, reflexes and lost connections classified); and,
only where the library itself is installed, real franky against a closed loopback port, against
franky-sim on 127.0.0.1, and real pyrealsense2 with no camera attached."""

from __future__ import annotations

import dataclasses
import importlib.util
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from fakes import FrankyScript, fake_franky, install

from robot.errors import RobotConnectionError
from robot.executor import Command, Outcome, RobotMode
from robot.fr3 import GLOBAL_DYNAMICS_FACTOR, FR3Executor
from robot.libfranka import fingertip_to_ee
from robot.safety import SafetyGate
from robot.session_log import SessionLog, read_log


@pytest.fixture
def plan(cell):
    gate = SafetyGate(cell)
    return gate.plan_primitive(np.array([0.53, 0.0, 0.05]), np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]))


def run(monkeypatch, cell, plan, script=None):
    fr = fake_franky(cell, script)
    install(monkeypatch, "franky", fr)
    with FR3Executor(cell, allow_no_realtime=True) as robot:
        result = robot.execute(plan)
    return fr, result


def test_fr3_sends_absolute_base_frame_targets_with_limits_from_the_cell(monkeypatch, cell, plan):
    fr, result = run(monkeypatch, cell, plan)
    r = fr.robot
    assert result.outcome is Outcome.ok and len(r.moves) == len(plan.commands)
    assert r.recoveries == 1 and r.relative_dynamics_factor == GLOBAL_DYNAMICS_FACTOR
    assert r.collision == ([cell.limits.collision_torque] * 7, [cell.limits.collision_force] * 6)
    assert r.realtime_config == "Ignore"
    from fakes import DEFAULT_F_T_EE

    tip_to_ee = fingertip_to_ee(cell, DEFAULT_F_T_EE)
    for motion, command in zip(r.moves[:-1], plan.commands[:-1], strict=True):
        assert motion.reference_type == "Absolute"  # never franky's end-effector-frame relative moves
        tip = (motion.target.matrix @ np.linalg.inv(tip_to_ee))[:3, 3]
        np.testing.assert_allclose(tip, command.target, atol=1e-9)
        v = motion.relative_dynamics_factor * GLOBAL_DYNAMICS_FACTOR * r.translation_velocity_limit
        assert v == pytest.approx(command.speed)  # the command's speed, through franky's factors
        assert motion.reactions and motion.reactions[0].condition.threshold == pytest.approx(
            cell.limits.force_stop**2
        )


def test_fr3_force_reaction_returning_normally_is_reported(monkeypatch, cell, plan):
    fr, result = run(monkeypatch, cell, plan, FrankyScript(faults={5: "force"}))
    assert result.outcome is Outcome.reaction_fired and result.failed.label == "w3 push 1"
    assert len(fr.robot.moves) == 5  # nothing after the stopped push


def test_fr3_every_move_carries_the_cells_deadline(monkeypatch, cell, plan):
    fr, result = run(monkeypatch, cell, plan, FrankyScript(faults={2: "deadline"}))
    assert result.outcome is Outcome.short_of_goal and "deadline" in result.message
    assert len(fr.robot.moves) == 2  # nothing after the move that ran out of time
    for motion in fr.robot.moves:  # the joint move home too
        deadlines = [r for r in motion.reactions if "t_rel" in r.condition.expr]
        assert [r.condition.threshold for r in deadlines] == [cell.limits.motion_timeout]


@pytest.mark.parametrize("fault, outcome", [("reflex", Outcome.reflex), ("comm_lost", Outcome.comm_lost)])
def test_fr3_reflex_and_connection_loss_classified(monkeypatch, cell, plan, fault, outcome):
    fr, result = run(monkeypatch, cell, plan, FrankyScript(faults={6: fault}))
    assert result.outcome is outcome and result.failed.label == "w4 push 2" and len(fr.robot.moves) == 6
    if fault == "reflex":
        assert result.errors == ("cartesian_reflex",)


def test_fr3_planner_failure_is_replanned_once_in_free_space_never_in_contact(monkeypatch, cell, plan):
    """franky's ruckig planner failing (a plain RuntimeError, no robot error) is never a traceback: a
    free-space move is replanned once to the same target; a second failure, or one in contact, ends
    the move short of its goal and nothing after it is sent."""
    fr, result = run(monkeypatch, cell, plan, FrankyScript(faults={1: "planner"}))
    assert result.outcome is Outcome.ok and len(fr.robot.moves) == len(plan.commands) + 1
    assert fr.robot.moves[0].target.matrix.tolist() == fr.robot.moves[1].target.matrix.tolist()

    fr, result = run(monkeypatch, cell, plan, FrankyScript(faults={1: "planner", 2: "planner"}))
    assert result.outcome is Outcome.short_of_goal and "motion planner failed" in result.message
    assert result.failed.label == plan.commands[0].label and len(fr.robot.moves) == 2

    push = next(i for i, c in enumerate(plan.commands) if c.in_contact)
    fr, result = run(monkeypatch, cell, plan, FrankyScript(faults={push + 1: "planner"}))
    assert result.outcome is Outcome.short_of_goal and result.failed is plan.commands[push]
    assert len(fr.robot.moves) == push + 1  # no second push


def test_fr3_absent_is_one_line(monkeypatch, cell):
    install(monkeypatch, "franky", fake_franky(cell, FrankyScript(absent=True)))
    with pytest.raises(RobotConnectionError, match="cannot connect to the FR3 at 172.16.0.2"):
        FR3Executor(cell).__enter__()


# --- the real franky library ----------------------------------------------------------------------------

HAVE_FRANKY = importlib.util.find_spec("franky") is not None
HAVE_FRANKY_SIM = HAVE_FRANKY and importlib.util.find_spec("franky_sim") is not None


def closed_port_cell(cell):
    import dataclasses

    return dataclasses.replace(cell, address="127.0.0.1", robot_type="fr3")


@pytest.mark.skipif(not HAVE_FRANKY, reason="franky-control is not installed (the subject of this test)")
def test_real_franky_robot_absent_on_a_closed_loopback_port(cell):
    with socket.socket() as s:  # make sure nothing listens on FCI's port
        if s.connect_ex(("127.0.0.1", 1337)) == 0:
            pytest.skip("something listens on 127.0.0.1:1337")
    t = time.time()
    with pytest.raises(RobotConnectionError, match="cannot connect to the FR3 at 127.0.0.1"):
        FR3Executor(closed_port_cell(cell), allow_no_realtime=True).__enter__()
    assert time.time() - t < 30


def _when_moving(executor, action, after_s: float = 0.3, moved_m: float = 0.001) -> threading.Thread:
    """Run ``action`` ``after_s`` into the next motion franky starts (a thread polling ``is_in_control``)
    and once the fingertip has moved ``moved_m``: on a loaded machine franky-sim runs slower than
    real time, and 0.3 s can be a fraction of a millimetre."""

    def wait_then_act():
        start = executor.fingertip()
        deadline = time.time() + 30
        while not executor.robot.is_in_control and time.time() < deadline:
            time.sleep(0.005)
        time.sleep(after_s)
        while np.linalg.norm(executor.fingertip() - start) < moved_m and time.time() < deadline:
            time.sleep(0.005)
        action()

    thread = threading.Thread(target=wait_then_act, daemon=True)
    thread.start()
    return thread


@pytest.mark.skipif(not HAVE_FRANKY_SIM, reason="franky-sim is not installed (the subject of this test)")
def test_fr3_against_franky_sim_on_loopback(cell, tmp_path):
    """Connect and set the limits; home by a joint move, then a push primitive's waypoints as absolute
    base-frame moves through ``execute``, each reached; an induced error recovered; then the connection
    lost mid-move when the server stops. franky-sim simulates no collisions, forces or reflexes (no
    error flag is ever set, its error recovery always succeeds), so the error induced is the one it can
    raise: a motion preempted by ``stop()`` from another thread (franky's ``ControlException``)."""
    with socket.socket() as s:
        if s.connect_ex(("127.0.0.1", 1337)) == 0:
            pytest.skip("something already listens on 127.0.0.1:1337")
    server = subprocess.Popen(
        [sys.executable, "-m", "franky_sim.run_server", "--hostname", "127.0.0.1", "--simulator", "mujoco"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.time() + 60
        while time.time() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", 1337)) == 0:
                    break
            time.sleep(0.5)
        else:
            pytest.fail("franky-sim did not start listening on 127.0.0.1:1337")
        c = closed_port_cell(cell)
        gate = SafetyGate(c)
        plan = gate.plan_primitive(np.array([0.53, 0.0, 0.05]), np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]))
        with SessionLog(tmp_path / "s") as log, FR3Executor(c, log=log, allow_no_realtime=True) as robot:
            limits = next(e for e in read_log(tmp_path / "s") if e["event"] == "limits_set")
            assert limits["collision_force_n"] == c.limits.collision_force
            assert limits["realtime"] == "ignored (--allow-no-realtime)"
            assert robot.robot.relative_dynamics_factor.velocity == pytest.approx(GLOBAL_DYNAMICS_FACTOR)
            assert robot.robot_mode() is RobotMode.idle and robot.current_errors() == ()

            home = Command(0, "home", tuple(gate.home_position), c.limits.transit_speed, "home")
            assert robot.send(home).outcome is Outcome.ok and robot.at_home(tol_rad=0.01)
            # the fingertip from franky's pose and F_T_EE is where the planner's kinematics put it
            np.testing.assert_allclose(robot.fingertip(), gate.home_position, atol=2e-3)

            result = robot.execute(plan)
            assert result.outcome is Outcome.ok and len(result.commanded) == len(plan.commands)
            assert robot.at_home(tol_rad=0.01)
            done = [e for e in read_log(tmp_path / "s") if e["event"] == "command_done"][1:]
            assert [e["label"] for e in done] == [cmd.label for cmd in plan.commands]
            for e, cmd in zip(done, plan.commands, strict=True):  # every waypoint reached, in the base frame
                np.testing.assert_allclose(e["position"], cmd.target, atol=2e-3, err_msg=cmd.label)

            start = robot.fingertip()
            down = Command(1, "transit", tuple(start - [0, 0, 0.10]), 0.05, "down 10 cm")
            stopper = _when_moving(robot, robot.stop)  # preempts the move: franky raises ControlException
            stopped = robot.send(down)
            stopper.join(timeout=30)
            assert stopped.outcome is Outcome.critical and "preempted" in stopped.message
            assert stopped.errors == ()  # no error flag: classify_errors() calls that critical
            # stopped part-way: it moved (on a loaded machine the stop can land within a millimetre of the start)
            assert start[2] - 0.10 + 0.01 < robot.fingertip()[2] < start[2] - 2e-4
            robot.recover()
            assert robot.robot_mode() is RobotMode.idle and robot.current_errors() == ()
            assert robot.send(down).outcome is Outcome.ok  # the same move again, after recovery
            assert robot.fingertip()[2] == pytest.approx(start[2] - 0.10, abs=2e-3)  # base frame: down

            # the cell's deadline, in seconds: a 10 cm move at 5 cm/s under a 0.5 s deadline stops
            # part-way (franky's REL_TIME is seconds; were it ms, the move would not start)
            robot.cell = dataclasses.replace(c, limits=dataclasses.replace(c.limits, motion_timeout=0.5))
            up = Command(3, "transit", tuple(start), 0.05, "up 10 cm")
            late = robot.send(up)
            assert late.outcome is Outcome.short_of_goal and "deadline of 0.5 s" in late.message
            assert start[2] - 0.10 + 5e-3 < robot.fingertip()[2] < start[2] - 0.03
            robot.cell = c
            robot.recover()

            back = Command(2, "transit", tuple(start), 0.05, "back up")
            killer = _when_moving(robot, server.terminate)
            lost = robot.send(back)
            killer.join(timeout=30)
            assert lost.outcome is Outcome.comm_lost and np.isnan(lost.position).all()
            server.wait(timeout=30)
    finally:
        if server.poll() is None:
            server.terminate()
            server.wait(timeout=30)


HAVE_REALSENSE = importlib.util.find_spec("pyrealsense2") is not None


@pytest.mark.skipif(not HAVE_REALSENSE, reason="pyrealsense2 is not installed (the subject of this test)")
def test_real_pyrealsense2_without_a_device_names_the_missing_camera(cell):
    from robot.connect import open_cameras
    from robot.errors import CameraError

    try:
        import pyrealsense2  # noqa: F401
    except ImportError as e:  # e.g. libusb-1.0 missing on this machine
        pytest.skip(f"pyrealsense2 cannot load here: {e}")
    with pytest.raises(CameraError, match="front \\(twin-front\\) is not connected"):
        with open_cameras(cell, "panda"):
            pass
