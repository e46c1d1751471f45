"""``hydo deploy`` as a user runs it: the real console entry point in a subprocess, with fake
``panda_py`` / ``pyrealsense2`` modules standing in for the hardware where a test needs a robot.
Every failure is one stderr line with a non-zero exit and no traceback."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hydo_cli.main import app
from robot.session_log import read_log

ROBOT_TESTS = Path(__file__).parent

RUNNER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    sys.path.insert(0, {tests!r})
    from rig import make_rig, push_towards_robot
    import robot.loop as L
    from fakes import PandaScript, fake_panda_py, fake_pyrealsense2, install

    rig = make_rig(Path({tmp!r}), Path({model!r}))
    install(None, "pyrealsense2", fake_pyrealsense2(rig.scene))
    install(None, "panda_py", fake_panda_py(rig.cell, PandaScript(faults={faults!r})))
    prepare = L.Deployment.prepare.__func__

    def prepared(cls, cfg, printer=None):  # a known-good push instead of the untrained policy's choice
        dep = prepare(cls, cfg, printer)
        push_towards_robot(dep)
        return dep

    L.Deployment.prepare = classmethod(prepared)
    from hydo_cli.main import main
    sys.argv = ["hydo", *sys.argv[1:]]
    main()
    """
)


def hydo(*args, timeout=300, env=None):
    return subprocess.run(
        [sys.executable, "-c", "from hydo_cli.main import main; main()", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )


def hydo_with_fakes(tmp: Path, model: Path, faults: dict, *args, env=None):
    rig_dir = tmp / "rig"
    rig_dir.mkdir(exist_ok=True)
    code = RUNNER.format(tests=str(ROBOT_TESTS), tmp=str(rig_dir), model=str(model), faults=faults)
    cmd = [sys.executable, "-c", code, "deploy", "--robot", "panda", "--model", str(model)]
    cmd += ["--cell", str(rig_dir / "cell.yaml"), "--goal", str(rig_dir / "goal.npz"), *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)


def one_line_error(r) -> str:
    assert "Traceback" not in r.stderr, r.stderr
    lines = [x for x in r.stderr.splitlines() if x.startswith("hydo: error:")]
    assert len(lines) == 1, r.stderr
    return lines[0]


def test_help_has_examples_and_subcommands():
    r = CliRunner().invoke(app, ["deploy", "--help"])
    assert r.exit_code == 0
    for text in (
        "--robot",
        "--dry-run",
        "--goal",
        "capture-background",
        "capture-goal",
        "hydo deploy --robot sim",
    ):
        assert text in r.output


def test_model_is_required_and_a_bad_model_is_one_line(tmp_path):
    r = hydo("deploy", "--robot", "sim")
    assert r.returncode == 2 and "--model" in r.stderr
    r = hydo("deploy", "--robot", "sim", "--model", str(tmp_path / "missing"))
    assert r.returncode == 1 and "does not exist" in one_line_error(r)


def test_real_arm_needs_a_goal(tiny_model, tmp_path):
    r = hydo("deploy", "--robot", "panda", "--model", str(tiny_model), "--log", str(tmp_path / "s"))
    assert r.returncode == 1 and "needs a goal" in one_line_error(r)


def test_model_registration_on_a_cell_needs_a_readable_object_mesh(tiny_model, tmp_path):
    base = ["deploy", "--robot", "panda", "--model", str(tiny_model), "--goal-offset", "0.05,0"]
    r = hydo(*base, "--registration", "model", "--log", str(tmp_path / "a"))
    assert r.returncode == 1 and "needs the object's mesh: --object-mesh" in one_line_error(r)
    bad = tmp_path / "broken.obj"
    bad.write_text("v 0 0 0\nf 1 2 3\n")
    r = hydo(*base, "--registration", "model", "--object-mesh", str(bad), "--log", str(tmp_path / "b"))
    assert r.returncode == 1 and "broken.obj" in one_line_error(r)
    r = hydo(*base, "--object-mesh", str(bad), "--log", str(tmp_path / "c"))  # auto: a mesh given is used
    assert r.returncode == 1 and "broken.obj" in one_line_error(r)
    r = hydo(*base, "--registration", "views", "--object-mesh", str(bad), "--log", str(tmp_path / "d"))
    assert r.returncode == 1 and "--object-mesh is for --registration model" in one_line_error(r)


def test_the_cli_choices_are_the_loops():
    """The typer enums restate ``robot.loop``'s choices (kept apart so that ``hydo --help`` does not
    import the deploy loop): they must not drift."""
    from hydo_cli.deploy import Observe, Registration
    from robot.loop import OBSERVATIONS, REGISTRATIONS

    assert tuple(o.value for o in Observe) == OBSERVATIONS
    assert tuple(r.value for r in Registration) == REGISTRATIONS


def test_model_observation_needs_model_registration(tiny_model, tmp_path):
    r = hydo(
        "deploy",
        "--robot",
        "sim",
        "--model",
        str(tiny_model),
        "--observe",
        "model",
        "--log",
        str(tmp_path / "a"),
    )
    assert r.returncode == 1 and "--observe model needs --registration model" in one_line_error(r)


def test_no_realtime_kernel_refused_unless_overridden(tiny_model, tmp_path):
    from robot.safety import has_realtime_kernel

    if has_realtime_kernel():
        pytest.skip("this machine runs a realtime kernel")
    r = hydo_with_fakes(tmp_path, tiny_model, {}, "--log", str(tmp_path / "s1"))
    assert r.returncode == 1 and "no realtime (PREEMPT_RT) kernel" in one_line_error(r)
    assert not [e for e in read_log(tmp_path / "s1") if e["event"] == "command"]
    r = hydo_with_fakes(
        tmp_path, tiny_model, {}, "--log", str(tmp_path / "s2"), "--allow-no-realtime", "--max-steps", "1"
    )
    assert r.returncode == 0, r.stderr
    events = [e["event"] for e in read_log(tmp_path / "s2")]
    assert "realtime_override" in events and events.index("realtime_override") < events.index("command")


def test_critical_error_exits_non_zero_with_what_to_do(tiny_model, tmp_path):
    r = hydo_with_fakes(
        tmp_path, tiny_model, {2: "critical"}, "--allow-no-realtime", "--log", str(tmp_path / "s")
    )
    line = one_line_error(r)
    assert r.returncode == 1 and "power_limit_violation" in line and "Not recovered automatically" in line


def test_ctrl_c_exits_130_after_stopping(tiny_model, tmp_path):
    r = hydo_with_fakes(
        tmp_path, tiny_model, {3: "interrupt"}, "--allow-no-realtime", "--log", str(tmp_path / "s")
    )
    assert r.returncode == 130, r.stderr
    assert "interrupted: motion stopped, cameras closed, log flushed" in r.stderr
    assert read_log(tmp_path / "s")[-1]["event"] == "interrupted"


def test_dry_run_prints_the_plan_table_and_connects_nothing(tiny_model, tmp_path):
    r = hydo_with_fakes(
        tmp_path, tiny_model, {1: "sigkill"}, "--dry-run", "--max-steps", "1", "--log", str(tmp_path / "s")
    )
    assert r.returncode == 0, r.stderr  # a move would have killed the process
    assert "dry run: nothing moves" in r.stdout and "w5 push 3" in r.stdout
    assert "motion commands sent" in r.stdout
