"""The robot libraries: the FR3 executor on a fake franky (absolute base-frame targets, a force
reaction that returns normally is still reported, reflexes and lost connections classified); and,
only where the library itself is installed, real franky against a closed loopback port, against
franky-sim on 127.0.0.1, and real pyrealsense2 with no camera attached."""

from __future__ import annotations

import importlib.util
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from robot.errors import RobotConnectionError
from robot.executor import Outcome
from robot.fakes import FrankyScript, fake_franky, install
from robot.fr3 import GLOBAL_DYNAMICS_FACTOR, FR3Executor
from robot.panda import fingertip_to_ee
from robot.safety import SafetyGate


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
    from robot.fakes import DEFAULT_F_T_EE

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


@pytest.mark.parametrize("fault, outcome", [("reflex", Outcome.reflex), ("comm_lost", Outcome.comm_lost)])
def test_fr3_reflex_and_connection_loss_classified(monkeypatch, cell, plan, fault, outcome):
    fr, result = run(monkeypatch, cell, plan, FrankyScript(faults={6: fault}))
    assert result.outcome is outcome and result.failed.label == "w4 push 2" and len(fr.robot.moves) == 6
    if fault == "reflex":
        assert result.errors == ("cartesian_reflex",)


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


@pytest.mark.skipif(not HAVE_FRANKY_SIM, reason="franky-sim is not installed (the subject of this test)")
def test_fr3_against_franky_sim_on_loopback(cell, tmp_path):
    """Connect, limits, an absolute base-frame move down and back, recovery; then the connection
    lost mid-move when the server stops (franky-sim simulates no collisions or forces)."""
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
        from robot.executor import Command

        with FR3Executor(c, allow_no_realtime=True) as robot:
            start = robot.fingertip()
            down = Command(0, "transit", tuple(start - [0, 0, 0.05]), 0.05, "down 5 cm")
            result = robot.send(down)
            assert result.outcome is Outcome.ok
            assert robot.fingertip()[2] == pytest.approx(
                start[2] - 0.05, abs=0.01
            )  # base frame: it went down
            robot.recover()
            server.terminate()
            server.wait(timeout=30)
            back = Command(1, "transit", tuple(start), 0.05, "back up")
            assert robot.send(back).outcome is Outcome.comm_lost
    finally:
        if server.poll() is None:
            server.terminate()
            server.wait(timeout=30)


HAVE_REALSENSE = importlib.util.find_spec("pyrealsense2") is not None


@pytest.mark.skipif(not HAVE_REALSENSE, reason="pyrealsense2 is not installed (the subject of this test)")
def test_real_pyrealsense2_without_a_device_names_the_missing_camera(cell):
    from robot.cameras import open_cameras
    from robot.errors import CameraError

    try:
        import pyrealsense2  # noqa: F401
    except ImportError as e:  # e.g. libusb-1.0 missing on this machine
        pytest.skip(f"pyrealsense2 cannot load here: {e}")
    with pytest.raises(CameraError, match="front \\(twin-front\\) is not connected"):
        with open_cameras(cell, "panda"):
            pass
