"""robot-safety.md's fault tests that need no hardware: each ends with a clear message and, where the
fault comes before motion, zero motion commands received by the (fake) robot.

The rig (``rig.py``): synthetic depth frames of a 6 cm box in the bin, the example cell at half camera
resolution, ``PandaExecutor`` on a fake ``panda_py`` that records every motion it receives.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from fakes import Box, PandaScript, fake_pyrealsense2, install
from rig import GOAL, START, make_rig, push_towards_robot

from robot.cameras import CameraSet, ReplayCamera
from robot.connect import open_cameras
from robot.errors import (
    CameraError,
    InputError,
    ModelLoadError,
    PerceptionError,
    RegistrationError,
    RobotConnectionError,
    RobotFaultError,
)
from robot.executor import Outcome
from robot.session_log import read_log
from sim.primitive import PrimitiveRejected


@pytest.fixture
def rig(tmp_path, tiny_model):
    return make_rig(tmp_path, tiny_model)


def events(rig, name=None):
    lines = read_log(rig.tmp / "session")
    return [e for e in lines if name is None or e["event"] == name]


# --- 1-3: cameras ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "case, match",
    [("missing", "twin-left.*is not connected"), ("usb2", "USB 2.1 link.*USB 3")],
)
def test_missing_camera_or_usb2_refused_before_the_robot_connects(rig, monkeypatch, case, match):
    rs = fake_pyrealsense2(rig.scene, usb={"twin-left": "2.1"} if case == "usb2" else None)
    if case == "missing":
        rs.state.present.discard("twin-left")
    install(monkeypatch, "pyrealsense2", rs)
    dep = rig.deployment()
    executor = rig.robot(monkeypatch)
    with pytest.raises(CameraError, match=match):
        dep.run(cameras=open_cameras(rig.cell, "panda"), executor=executor)
    assert rig.pp.connects == 0 and executor.commands_sent == 0
    assert rs.state.running == set()  # the cameras that did open were stopped again


def test_frame_timeout_resets_once_then_stops_naming_the_camera(rig, monkeypatch):
    # Frames 1-5 are the warm-up, 6 the first capture; every wait from the 7th on times out.
    rs = fake_pyrealsense2(rig.scene, timeouts={"twin-front": set(range(7, 100))})
    install(monkeypatch, "pyrealsense2", rs)
    dep = rig.deployment(max_steps=2)
    push_towards_robot(dep)
    with pytest.raises(CameraError, match="front \\(twin-front\\) timed out twice"):
        dep.run(cameras=open_cameras(rig.cell, "panda"), executor=rig.robot(monkeypatch))
    assert rs.state.resets == ["twin-front"]  # exactly one hardware reset
    assert rs.state.running == set()  # every pipeline stopped
    # The next run opens the cameras without "device busy".
    with open_cameras(rig.cell, "panda"):
        pass


def test_stale_frame_recaptured_once_then_refused(rig, monkeypatch):
    dep = rig.deployment()
    with pytest.raises(CameraError, match="stale frame.*refused after one re-capture"):
        rig.run(monkeypatch, dep, camera_script=["stale", "stale"])
    assert rig.received() == []
    assert len(events(rig, "frame_discarded")) == 2


def test_one_stale_frame_is_discarded_and_recaptured(rig, monkeypatch):
    dep = rig.deployment(max_steps=1)
    push_towards_robot(dep)
    rig.run(monkeypatch, dep, camera_script=["stale"])
    assert len(events(rig, "frame_discarded")) == 1 and len(events(rig, "outcome")) == 1


def test_slow_cameras_do_not_make_the_first_frame_stale(rig, monkeypatch):
    # Cameras answer one after another; on a loaded host the later ones can take longer than the
    # frame-age limit. The first camera's frame was fresh when it was asked for: keep it.
    import fakes

    plain = fakes.ScriptedCamera.capture
    n_cams = len(rig.cell.cameras)
    pause = 1.2 * rig.cell.perception.max_frame_age / max(n_cams - 1, 1)

    def slow_capture(cam):
        frame = plain(cam)
        if cam is not rig.cams[0]:
            time.sleep(pause)
        return frame

    monkeypatch.setattr(fakes.ScriptedCamera, "capture", slow_capture)
    dep = rig.deployment(max_steps=1)
    push_towards_robot(dep)
    rig.run(monkeypatch, dep)
    assert n_cams >= 2 and events(rig, "frame_discarded") == [] and len(events(rig, "outcome")) == 1


def test_arm_away_from_home_means_no_capture(rig, monkeypatch):
    dep = rig.deployment()
    executor = rig.robot(monkeypatch)
    cams = rig.cameras()
    real_connect = executor.connect

    def connect():
        real_connect()
        rig.arm.q = rig.arm.q + 0.5  # the arm is somewhere over the bin, in the cameras' view

    executor.connect = connect
    with pytest.raises(CameraError, match="not at its home pose"):
        dep.run(cameras=cams, executor=executor)
    assert rig.received() == [] and all(c.captures == 0 for c in rig.cams)


# --- 4-7: perception and registration --------------------------------------------------------------------


def test_nan_depth_refused_naming_the_camera(rig, monkeypatch):
    dep = rig.deployment()
    with pytest.raises(PerceptionError, match="camera front \\(twin-front\\): depth tensor has 100 NaN/inf"):
        rig.run(monkeypatch, dep, camera_script=["nan"])
    assert rig.received() == []
    assert (rig.tmp / "session" / "steps" / "e000-s00.npz").exists()  # the capture is still logged


def test_nan_policy_output_and_nan_normals_refused(rig, monkeypatch):
    dep = rig.deployment()
    dep.policy.act = lambda p, f, r, **feasibility: (0, np.array([np.nan, 0.0, 0.0], np.float32), {})
    with pytest.raises(InputError, match="`motion` is not a finite"):
        rig.run(monkeypatch, dep)
    assert rig.received() == []
    from robot.safety import SafetyGate

    obs = {"points": np.zeros((48, 3)), "features": np.zeros((48, 4)), "normals": np.ones((32, 3))}
    obs["features"][:32, 0] = 1
    obs["normals"][3] = np.nan
    with pytest.raises(InputError, match="`normals` contains 3 NaN/inf"):
        SafetyGate.check_observation(obs, 32, 16)


def test_empty_mask_refused_and_capture_logged(rig, monkeypatch):
    rig.scene.box = None
    dep = rig.deployment()
    with pytest.raises(PerceptionError, match="empty or tiny"):
        rig.run(monkeypatch, dep)
    assert rig.received() == []
    steps = rig.tmp / "session" / "steps" / "e000-s00.npz"
    with np.load(steps) as z:
        assert "depth/twin-front" in z.files
    assert events(rig, "refused")[0]["error"] == "PerceptionError"


def test_bumped_camera_refused_recapture_background(rig, monkeypatch):
    rig.scene.bump("twin-right", 0.02, 2.0)
    dep = rig.deployment()
    with pytest.raises(
        PerceptionError, match="right \\(twin-right\\).*no longer matches.*capture-background"
    ):
        rig.run(monkeypatch, dep)
    assert rig.received() == []


def test_registration_failure_refused_with_residuals(rig, monkeypatch):
    rig.scene.box = Box(size=(0.16, 0.03, 0.03), xy=(0.54, 0.0))  # not the goal's object
    dep = rig.deployment()
    with pytest.raises(RegistrationError, match="inlier RMS .* mm .*inliers"):
        rig.run(monkeypatch, dep)
    assert rig.received() == []


# --- 8, 11, 19: plans and models ---------------------------------------------------------------------------


def test_plan_leaving_the_workspace_refused_naming_waypoint_axis_bound(rig, monkeypatch):
    rig.scene.box = Box(xy=(0.705, 0.0))  # near the far wall; pushing outward
    dep = rig.deployment()
    push_towards_robot(dep, motion=(1.0, 0.0, 0.0))
    with pytest.raises(
        PrimitiveRejected, match="waypoint \\d x=0\\.7\\d\\d m is above the workspace bound 0.753 m"
    ):
        rig.run(monkeypatch, dep)
    assert rig.received() == []


@pytest.mark.parametrize("damage", ["truncate", "hash"])
def test_bad_model_refused_before_any_device_opens(rig, monkeypatch, tmp_path, damage):
    model = tmp_path / "model"
    shutil.copytree(rig.model, model)
    if damage == "truncate":
        data = (model / "actor.onnx").read_bytes()
        (model / "actor.onnx").write_bytes(data[: len(data) // 3])
    else:
        m = json.loads((model / "manifest.json").read_text())
        m["sha256"]["critic.onnx"] = "0" * 64
        (model / "manifest.json").write_text(json.dumps(m))
    rs = fake_pyrealsense2(rig.scene)
    install(monkeypatch, "pyrealsense2", rs)
    rig.robot(monkeypatch)
    with pytest.raises(ModelLoadError, match="sha256|actor.onnx"):
        rig.deployment(model=model)
    assert rs.state.started == 0 and rig.pp.connects == 0
    assert not (rig.tmp / "session").exists()


def test_dry_run_moves_nothing_prints_plans_and_still_refuses_a_bad_plan(rig, monkeypatch):
    dep = rig.deployment(dry_run=True, max_steps=3)
    push_towards_robot(dep, motion=[(-1.0, 0, 0), (-1.0, 0, 0), (1.0, 0, 0)])
    plans = []
    dep.on_plan = lambda ep, step, plan: plans.append(plan)

    def near_wall(scene):
        scene.box = Box(xy=(0.705, 0.0))

    # captures 1-2 (cameras 1-3 each): the box at the start; capture 3 (step 2): near the far wall
    script = [None, None, near_wall]
    with pytest.raises(PrimitiveRejected, match="above the workspace bound"):
        rig.run(monkeypatch, dep, camera_script=script)
    assert rig.pp.connects == 0 and rig.received() == []  # a dry run never even connects
    assert len(plans) == 2 and plans[0].table_rows()[0][1] == "transit"
    assert [e["event"] for e in events(rig) if e["event"] in ("plan", "refused")] == [
        "plan",
        "plan",
        "refused",
    ]


# --- 12-15, 18: robot faults ----------------------------------------------------------------------------


def test_robot_absent_one_line_and_cameras_closed(rig, monkeypatch):
    dep = rig.deployment()
    with pytest.raises(RobotConnectionError, match="cannot connect to the Panda at 172.16.0.2.*FCI"):
        rig.run(monkeypatch, dep, PandaScript(absent=True))
    assert rig.pp.connects == 1 and all(c.closed == 1 and not c.is_open for c in rig.cams)


def test_connection_lost_mid_push_stops_without_reconnecting(rig, monkeypatch):
    dep = rig.deployment(max_steps=3)
    push_towards_robot(dep)
    with pytest.raises(RobotConnectionError, match="lost during 'w3 push 1'.*not reconnecting"):
        rig.run(monkeypatch, dep, PandaScript(faults={5: "comm_lost"}))
    assert rig.pp.connects == 1 and len(rig.received()) == 5
    commands = events(rig, "command")
    assert commands[-1]["label"] == "w3 push 1"  # the log's last command is the one that was lost


@pytest.mark.parametrize("fault", ["reflex", "reflex_latched"])
def test_reflex_on_push_2_recovers_once_retracts_and_replans(rig, monkeypatch, fault):
    dep = rig.deployment(max_steps=2)
    push_towards_robot(dep)
    executor = rig.run(monkeypatch, dep, PandaScript(faults={6: fault}))
    received = rig.received()
    # moves 1-6: transit, w0, w1, w2, push 1, push 2 (reflex); push 3 is never sent;
    # 7-8: the checked retract (straight up, home); 9-18: the next primitive, re-planned.
    assert rig.arm.recovers == 1 + 1  # one on connect (franky's ritual), one after the reflex
    assert [k for k, _ in received[6:8]] == ["cartesian_from", "joint"]
    assert len(received) == 8 + 10
    recovery = events(rig, "recovery")
    assert len(recovery) == 1 and recovery[0]["mode"] == "reflex"
    if fault == "reflex_latched":
        assert recovery[0]["errors"] == ["cartesian_reflex"]  # last_motion_errors, flags already cleared
    labels = [e["label"] for e in events(rig, "command")]
    assert labels[:6] == ["over w0", "w0 pre-contact", "w1 approach", "w2 contact", "w3 push 1", "w4 push 2"]
    assert labels[6:8] == ["retract up", "home"] and "w5 push 3" not in labels[:8]
    assert executor.commands_sent == len(received)
    observations = [e["step"] for e in events(rig, "observation")]
    assert observations == [0, 1, 2]  # re-observed after the recovery


def test_fourth_reflex_in_an_episode_stops_the_run(rig, monkeypatch):
    dep = rig.deployment(max_steps=6)
    push_towards_robot(dep)
    # Each primitive: 6 moves to push 2, then a 2-move retract after its reflex.
    faults = {6 + 8 * k: "reflex" for k in range(4)}
    with pytest.raises(RobotFaultError, match="reflex number 4 in this episode"):
        rig.run(monkeypatch, dep, PandaScript(faults=faults))
    assert len(events(rig, "recovery")) == 3


def test_retract_starts_where_a_stop_left_the_arm_just_outside_the_workspace(cell):
    """A reflex can leave the fingertip a millimetre past the workspace box (the twin: x 1.2 mm under its
    low bound after a 73 N reflex). The straight-up retract must still be planned from there: refusing
    it stopped a twin evaluation with ``PrimitiveRejected`` and would leave a real arm in the bin.
    Farther out than the tolerance is a fault a person clears, named in one line."""
    from robot.safety import RETRACT_START_TOLERANCE_M, SafetyGate

    gate = SafetyGate(cell)
    lo = np.asarray(cell.workspace.low)
    start = np.array([lo[0] - 0.0012, 0.0, cell.workspace.floor_z + 0.03])
    plan = gate.plan_retract(start, cell.home_joints)
    assert [c.label for c in plan.commands] == ["retract up", "home"]
    up = np.asarray(plan.commands[0].target)
    np.testing.assert_allclose(up[:2], start[:2])  # straight up: no further out in x or y
    assert up[2] == pytest.approx(cell.approach_z)
    far = start - [RETRACT_START_TOLERANCE_M + 0.01, 0.0, 0.0]
    with pytest.raises(
        RobotFaultError,
        match=r"more than 10 mm outside the workspace .*x=.*below the workspace bound.*guide the arm home",
    ):
        gate.plan_retract(far, cell.home_joints)


def test_silent_false_detected_with_raise_error_and_classified(rig, monkeypatch):
    dep = rig.deployment(max_steps=1)
    push_towards_robot(dep)
    rig.run(monkeypatch, dep, PandaScript(faults={10: "false"}))  # the joint move home returns False
    outcome = events(rig, "outcome")[0]
    assert outcome["outcome"] == "reflex" and outcome["failed"]["label"] == "home"
    assert outcome["errors"] == ["cartesian_reflex"]
    assert len(events(rig, "recovery")) == 1


@pytest.mark.parametrize(
    "fault, match", [("critical", "power_limit_violation.*power supply"), ("user_stop", "user_stop.*release")]
)
def test_critical_errors_are_not_recovered(rig, monkeypatch, fault, match):
    dep = rig.deployment(max_steps=2)
    push_towards_robot(dep)
    with pytest.raises(RobotFaultError, match=f"{match}.*Not recovered automatically"):
        rig.run(monkeypatch, dep, PandaScript(faults={5: fault}))
    assert rig.arm.recovers == 1  # only franky's-ritual recovery on connect
    assert len(rig.received()) == 5


def test_force_stop_on_the_fake_panda_retracts(rig, monkeypatch):
    dep = rig.deployment(max_steps=1)
    push_towards_robot(dep)
    rig.run(monkeypatch, dep, PandaScript(faults={5: "force"}))
    out = events(rig, "outcome")[0]
    assert out["outcome"] == Outcome.reaction_fired.value and out["failed"]["label"] == "w3 push 1"
    lim = rig.cell.limits
    assert lim.force_stop < out["peak_force_n"] <= 1.2 * lim.force_stop
    assert [e["label"] for e in events(rig, "command")][5:] == ["retract up", "home"]


def test_ctrl_c_stops_the_arm_closes_cameras_and_flushes_the_log(rig, monkeypatch):
    rs = fake_pyrealsense2(rig.scene)  # starting a pipeline that was never stopped: "device busy"
    install(monkeypatch, "pyrealsense2", rs)
    dep = rig.deployment(max_steps=2)
    push_towards_robot(dep)
    executor = rig.robot(monkeypatch, PandaScript(faults={3: "interrupt"}))
    with pytest.raises(KeyboardInterrupt):
        dep.run(cameras=open_cameras(rig.cell, "panda"), executor=executor)
    assert rig.arm.controller is None  # stopped
    assert rs.state.started >= len(rig.cell.cameras) and rs.state.running == set()  # every pipeline stopped
    assert events(rig)[-1]["event"] == "interrupted"
    with open_cameras(rig.cell, "panda") as cams:  # the next run opens the same devices and captures
        assert [f.serial for f in cams.capture()] == [c.serial for c in rig.cell.cameras]


# --- 20: SIGKILL ----------------------------------------------------------------------------------------------


def test_sigkill_mid_step_leaves_a_log_line_before_every_command_and_a_replayable_session(rig):
    record = rig.tmp / "received.txt"
    script = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(os.path.dirname(__file__))!r})
        from rig import make_rig, push_towards_robot
        from fakes import PandaScript, fake_panda_py, install
        from robot.panda import PandaExecutor
        from pathlib import Path
        rig = make_rig(Path({str(rig.tmp / "kill")!r}), Path({str(rig.model)!r}))
        install(None, "panda_py", fake_panda_py(rig.cell, PandaScript(faults={{7: "sigkill"}}, record_path={str(record)!r})))
        dep = rig.deployment(max_steps=2, log_dir=Path({str(rig.tmp / "session")!r}))
        push_towards_robot(dep)
        dep.run(cameras=rig.cameras(), executor=PandaExecutor(rig.cell, allow_no_realtime=True))
        """
    )
    (rig.tmp / "kill").mkdir()
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    received = record.read_text().splitlines()
    assert len(received) == 7
    lines = read_log(rig.tmp / "session")
    commands = [e for e in lines if e["event"] == "command"]
    assert len(commands) == len(received)  # every received motion has its line, written before it
    assert commands[-1]["label"] == "w5 push 3"
    # the replay camera plays the session back
    cam = ReplayCamera(rig.cell.cameras[0], rig.tmp / "session")
    with CameraSet([cam]):
        f = cam.capture()
    assert f.depth.shape == (rig.cell.cameras[0].height, rig.cell.cameras[0].width)
    assert np.isfinite(f.depth).all() and (f.depth > 0).mean() > 0.9


def test_start_and_goal_boxes_differ():
    assert START.xy != GOAL.xy  # the rig's episodes never start at their goal


def test_speed_scale_slows_every_logged_command(rig, monkeypatch):
    dep = rig.deployment(speed_scale=0.5)
    push_towards_robot(dep)
    rig.run(monkeypatch, dep)
    commands = events(rig, "command")
    lim = rig.cell.limits
    assert commands and all(c["speed"] <= 0.5 * lim.transit_speed + 1e-12 for c in commands)
    assert {c["speed"] for c in commands if c["kind"] == "push"} == {0.5 * lim.push_speed}
