"""The ``hydo`` command line: help, baselines, and one-line errors with non-zero exits."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hydo_cli.main import app

runner = CliRunner()
ROOT = Path(__file__).resolve().parent.parent
OLD_RUN = str(ROOT / "tests" / "data" / "old-run-v0")
MODEL = str(ROOT / "models" / "hydo-cm-planar")  # an existing export: never overwritten without --force


def hydo(*args, cwd=None):
    """Run the real console entry point (``main``), which maps known errors to one line, as a user's
    shell would: from any folder (``cwd``), this checkout's packages, no ``HYDO_DEBUG`` tracebacks."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("HYDO_DEBUG", None)
    return subprocess.run(
        [sys.executable, "-c", "from hydo_cli.main import main; main()", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=300,
    )


def test_help_lists_the_four_commands():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for cmd in ("train", "eval", "export", "deploy"):
        assert cmd in result.output
    for cmd in ("train", "eval", "export", "deploy"):
        r = runner.invoke(app, [cmd, "--help"])
        assert r.exit_code == 0 and "Usage" in r.output, cmd


def test_eval_heuristic_writes_json(tmp_path):
    out = tmp_path / "h.json"
    r = hydo("eval", "heuristic", "--objects", "cube", "--episodes", "3", "--json", str(out))
    assert r.returncode == 0, r.stderr
    data = json.loads(out.read_text())
    run = data["runs"][0]  # one entry per TARGET (tests/test_eval.py covers the rest of the schema)
    detail = run["episodes_detail"]
    assert data["episodes"] == 3 and len(detail) == 3 and run["stochastic"] is False
    assert run["success_rate"] == pytest.approx(sum(e["success"] for e in detail) / 3)


def test_eval_video(tmp_path):
    import cv2

    out = tmp_path / "v.mp4"
    r = hydo("eval", "random", "--objects", "cube", "--episodes", "1", "--video", str(out))
    assert r.returncode == 0, r.stderr
    cap = cv2.VideoCapture(str(out))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) >= 2


@pytest.mark.parametrize(
    "args, message",
    [
        (["eval", "no/such/run"], "neither a baseline"),
        (["eval", "heuristic", "--objects", "no_such_object"], "no_such_object"),
        (["eval", "heuristic", "--episodes", "0"], "--episodes"),
        (["train", "--config", "missing.toml"], "missing.toml"),
        (["train", "--resume", "no/such/run"], "not a run directory"),
        (["train", "--minutes", "-1"], "--minutes"),
        (["train", "--resume", OLD_RUN, "--seed", "3"], "drop --seed"),
        (["eval", "heuristic", "--json", OLD_RUN + "/config.json/x.json"], "is a file, not a folder"),
        (["eval", "heuristic", "--json", "."], "is a folder"),
        (["export", OLD_RUN, "--out", MODEL], "already holds files"),
    ],
)
def test_bad_input_is_one_line_and_nonzero(args, message, tmp_path):
    r = hydo(*args, cwd=tmp_path)
    assert r.returncode != 0
    assert "Traceback" not in r.stderr, r.stderr
    assert message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_resume_extends_the_minutes_budget(tmp_path):
    """--minutes on --resume replaces the run's budget (it counts the run's time over its resumes)."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(OLD_RUN, run)
    # the fixture keeps no replay.npz (size): --resume refuses to go on with an empty buffer unless told
    r = hydo("train", "--resume", str(run), "--minutes", "0.001", cwd=tmp_path)
    assert r.returncode == 1 and "replay.npz is missing" in r.stderr and "Traceback" not in r.stderr
    # the old run has 120 of 120 steps and no budget: a budget of 0.001 min ends at once, recorded
    r = hydo(
        "train", "--resume", str(run), "--minutes", "0.001", "--threads", "1", "--fresh-replay", cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    saved = json.loads((run / "config.json").read_text())
    assert saved["max_minutes"] == 0.001


def test_user_mesh_folder_errors_name_the_file(tmp_path):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "broken.obj").write_text("this is not a mesh\n")
    r = hydo("eval", "heuristic", "--objects", str(tmp_path / "meshes"), "--episodes", "1")
    assert r.returncode != 0 and "broken.obj" in r.stderr and "Traceback" not in r.stderr


# --- exit codes and a quiet export (issue 17) ---------------------------------------------------------


def test_sigterm_exits_130_like_ctrl_c(tmp_path):
    """SIGTERM during a command is Ctrl-C: cleanup runs and the exit code is 130 (not -15, not 1)."""
    import signal
    import time

    # known_errors() first: main's imports are then cached, so its handler is in place right after "ready"
    code = (
        "from hydo_cli.errors import known_errors; from hydo_cli.main import main; known_errors(); "
        "print('ready', flush=True); main()"
    )
    p = subprocess.Popen(
        [sys.executable, "-c", code, "eval", "heuristic", "--objects", "cube", "--episodes", "500"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    assert p.stdout.readline().strip() == "ready"
    time.sleep(2.0)  # main has installed its handler; the episodes are running
    assert p.poll() is None, p.communicate()
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "Traceback" not in err, err


def test_deploy_with_a_bin_out_of_reach_exits_1_before_anything_opens(tmp_path):
    import yaml

    cell = yaml.safe_load((ROOT / "robot" / "cell.example.yaml").read_text())
    for key in (("bin", "center_m"), ("workspace", "low_m"), ("workspace", "high_m")):
        cell[key[0]][key[1]][0] += 0.6  # 1.1 m in front of the base: beyond a Panda's reach
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(cell))
    r = hydo("deploy", "--robot", "sim", "--model", MODEL, "--cell", "cell.yaml", "--log", "s", cwd=tmp_path)
    assert r.returncode == 1, r.stderr
    assert "beyond the panda arm's reach" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "s").exists()


def test_export_prints_no_exporter_warnings(tmp_path):
    """A normal export prints none of torch's known exporter warnings (they are filtered only around
    the export call: hydo_cli.onnx_export.KNOWN_EXPORT_WARNINGS)."""
    code = (
        "from hydo_cli.config import TrainConfig, agent_config\n"
        "from hydo_cli.onnx_export import export_agent\n"
        "from models.algos import HybridAgent\n"
        "tiny = dict(feature_dim=16, encoder_hidden=16, encoder_global=16, actor_hidden=16, critic_hidden=16)\n"
        "cfg = TrainConfig(algo='hydo-cm', objects='cube', goals='planar', n_obj=32, n_bg=16, agent=tiny)\n"
        f"export_agent(HybridAgent(agent_config(cfg)), cfg, 'test', {str(tmp_path / 'm')!r}, n_checks=8)\n"
    )
    r = subprocess.run(
        [sys.executable, "-W", "default", "-c", code], capture_output=True, text=True, cwd=ROOT
    )
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip() == "", r.stderr
    assert (tmp_path / "m" / "manifest.json").exists()


def test_deploy_log_that_cannot_be_a_folder_is_refused_before_anything_runs(tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("user data\n")
    model = Path(__file__).resolve().parents[1] / "models" / "hydo-cm-planar"
    for log in (blocker, blocker / "session"):
        r = hydo("deploy", "--robot", "sim", "--model", str(model), "--episodes", "1", "--log", str(log))
        assert r.returncode == 1 and "is a file" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert blocker.read_text() == "user data\n"
