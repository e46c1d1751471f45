"""Every bench/ script runs end to end for a moment and writes the JSON its docstring promises.

Smoke tests only: speed figures are measured by running the scripts themselves (never asserted here)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
OLD_RUN = ROOT / "tests" / "data" / "old-run-v0"  # a tiny run with metrics.jsonl and eval.jsonl
# three episodes of a 6D ladder's twin log (seed 5): episode 0 is a mug the registration called a
# success 6.9 cm from its goal (inliers 0.83, goal coverage 0.93); 1 and 2 are true successes
TWIN_SESSION = ROOT / "tests" / "data" / "twin-session-v0"
# py-spy raw samples of one training worker (session 56's seed-0 run), trimmed to five stacks
PYSPY_RAW = ROOT / "tests" / "data" / "pyspy-worker-raw.txt"
SHIPPED_6D_CONTACTS = json.loads((ROOT / "models" / "hydo-cm-6d" / "manifest.json").read_text()).get(
    "contacts", "hydo"
)

CASES = {
    "curves.py": ([str(OLD_RUN)], lambda d: d),
    "checkpoint.py": (
        ["--capacity", "200", "--interval", "20", "--segments", "3", "--n-obj", "16", "--n-bg", "16"],
        lambda d: d["snapshot_s"] > 0 and d["segment_s"] > 0 and d["segment_mb"] < d["shard_mb"],
    ),
    "learner.py": (["--algos", "hydo-cm", "--seconds", "1", "--threads", "1"], lambda d: d),
    "inference.py": (["--runs", "3"], lambda d: d["ort_ms_median"] > 0),
    "lookahead.py": (
        ["--candidates", "4", "--episodes", "1"],
        lambda d: "C=4" in d and d["meta"]["contacts"] == "hydo",
    ),
    "sim.py": (["--seconds", "1"], lambda d: d["mesh_steps_per_s"] > 0),
    "verdict.py": (
        [str(TWIN_SESSION)],
        lambda d: (
            d["stops"] == {"success (false) -> uncertain": 1, "success (true) -> success": 2}
            # episode 0's false claim came at the step limit, where the current verdict reports it
            # ambiguous: a failure by the truth, and no longer a false success
            and d["replayed"] == {"success": 2, "failure": 1, "success_rate": pytest.approx(2 / 3)}
        ),
    ),
    "registration.py": (
        ["--episodes", "2"],
        lambda d: (
            d["start"]["all"]["n"] == 2
            and d["near"]["all"]["adds_median_mm"] < 10
            # point for point (ADD) is never nearer than to the nearest point (ADD-S)
            and d["start"]["all"]["flow_add_median_mm"] >= d["start"]["all"]["adds_median_mm"]
        ),
    ),
    "render_gap.py": (
        [
            "--model",
            str(ROOT / "models" / "hydo-cm-6d"),
            "--episodes",
            "1",
            "--policy-seed",
            "9",
            "--variants",
            "mesh-all,mesh-pca,render-mesh-normals,mesh-render-bg,render-grid-bg,mesh-pose-noise",
        ],
        lambda d: (
            set(d)
            == {
                "mesh-all",
                "mesh-pca",
                "render-mesh-normals",
                "mesh-render-bg",
                "render-grid-bg",
                "mesh-pose-noise",
                "meta",
            }
            and len(d["mesh-all"]["successes"]) == 1
        ),
    ),
    "outside_meshes.py": (
        ["--model", str(ROOT / "models" / "hydo-cm-6d"), "--episodes", "2", "--per-kind", "1"],
        lambda d: (
            len(d["meta"]["meshes"]) == 9  # one blob, rock and multi-part body, six household shapes
            and sum(n for _, n in d["outside"]["per_object"].values()) == 2
            and d["gap"] == pytest.approx(d["unseen"]["success_rate"] - d["outside"]["success_rate"])
            # both sets play in the contacts the model was trained in (its manifest's; hydo if unsaid)
            and d["outside"]["contacts"] == d["unseen"]["contacts"] == SHIPPED_6D_CONTACTS
        ),
    ),
    "push_forces.py": (
        ["--model", str(ROOT / "models" / "hydo-cm-6d"), "--episodes", "2"],
        lambda d: (
            sum(v["primitives"] for k, v in d.items() if k != "meta") > 0
            and all(0 <= v["force_stopped"] <= 1 for k, v in d.items() if k != "meta")
        ),
    ),
    "run_profile.py": (
        # one worker's py-spy samples: 6 in an update (backward), 2 in an env step's push, 1 waiting
        # at a gradient sync, 1 in an evaluation's env step; 5 of an idle thread outside the loop
        ["--raw", str(PYSPY_RAW)],
        lambda d: (
            d["workers"][0]["loop_samples"] == 10
            and {k: v for k, v in d["workers"][0]["parts"].items() if v}
            == {
                "update": pytest.approx(0.6),
                "env step": pytest.approx(0.2),
                "gradient sync: waiting": pytest.approx(0.1),
                "evaluation": pytest.approx(0.1),  # its env step is not counted as training's
            }
            and d["workers"][0]["env_step"] == {"push physics": 1.0}
            and d["workers"][0]["update_lines"][0]["line"] == "models/algos.py:673"
        ),
    ),
    "worker_balance.py": (
        ["--seconds", "3", "--envs", "2"],
        lambda d: (
            d["iterations"] >= 3
            and d["meta"]["contacts"] == SHIPPED_6D_CONTACTS  # the model's own contacts
            # two workers of one env each: a worker's env time is one step's, and the spread, the
            # mean |E_0 - E_1|, is at most the mean E_0 + E_1
            and d["worker_env_ms"] == pytest.approx(d["env_step_ms"])
            and 0 < d["spread_ms"] <= 2 * d["env_step_ms"]
            and d["us_per_physics_step"]
            and all(v > 0 for v in d["us_per_physics_step"].values())
            and set(d["predictors"])
            == {
                "planned controls",
                "object",
                "object x planned controls",
                "object x physics steps (after)",
                "previous iteration",
            }
        ),
    ),
    "trainer.py": (
        ["--seconds", "15", "--goals", "planar", "--objects", "cube", "--log-every", "8"]
        + ["--config", str(ROOT / "tests" / "data" / "bench-trainer.toml")]  # batch_size = 8
        + [
            x
            for line in ("n_envs = 4", "n_obj = 32", "n_bg = 32", "learning_starts = 16")
            for x in ("--set", line)
        ],
        lambda d: (
            d["updates_speedup"] > 0
            and d["default"]["updates_per_env_step"]
            == pytest.approx(d["serial"]["updates_per_env_step"], rel=0.2)
            # the config's settings reach both of this tree's layouts; its run length does not
            and d["default"]["batch_size"] == d["serial"]["batch_size"] == 8
            and d["meta"]["config_settings"] == {"batch_size": 8, "agent": {"policy_delay": 1}}
            # two workers wait at their syncs for some share of the time; one has none to wait at
            and 0.0 <= d["default"]["sync_wait_share"] <= 1.0
            and d["serial"]["sync_wait_share"] is None
        ),
    ),
}


def test_every_bench_script_has_a_smoke_case():
    # bench/_*.py are helpers the scripts import, not scripts
    assert sorted(p.name for p in (ROOT / "bench").glob("[!_]*.py")) == sorted(CASES)


def _run_bench(script: str, args: list[str], tmp_path) -> dict:
    """Run ``bench/<script> ARGS --json FILE`` in ``tmp_path``; its JSON, once it exited 0 cleanly."""
    out = tmp_path / "bench.json"
    r = subprocess.run(
        [sys.executable, str(ROOT / "bench" / script), *args, "--json", str(out)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    return json.loads(out.read_text())


@pytest.mark.slow
@pytest.mark.parametrize("script", sorted(CASES))
def test_bench_script_runs(script, tmp_path):
    args, check = CASES[script]
    data = _run_bench(script, args, tmp_path)
    assert data and check(data), data


def test_verdict_reads_a_ladder_rung_split_into_sessions(tmp_path):
    """``hydo deploy ladder --jobs 2`` leaves a twin rung as one session per piece of its episodes
    (``twin/e000-049``, ...): given the rung's folder, the bench reads every piece."""
    import shutil

    for piece in ("e000-002", "e003-005"):
        shutil.copytree(TWIN_SESSION, tmp_path / "twin" / piece)
    data = _run_bench("verdict.py", [str(tmp_path / "twin")], tmp_path)
    assert data["stops"] == {"success (false) -> uncertain": 2, "success (true) -> success": 4}
    empty = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "verdict.py"), str(tmp_path)], capture_output=True, text=True
    )
    assert empty.returncode != 0 and "no log.jsonl" in empty.stderr


@pytest.mark.slow
def test_trainer_bench_against_a_baseline_commit(tmp_path):
    """``bench/trainer.py --baseline REV`` runs REV's loop (a temporary git worktree, removed again)
    beside this tree's and reports sample-gradients/h for both."""
    args, _ = CASES["trainer.py"]
    data = _run_bench("trainer.py", [*args, "--baseline", "HEAD"], tmp_path)
    assert set(data["runs"]) == {"baseline", "default"} and data["meta"]["baseline"] == "HEAD"
    for name in ("baseline", "default"):
        row = data[name]
        assert row["sample_gradients_per_hour"] == pytest.approx(row["updates_per_hour"] * row["batch_size"])
        assert row["updates_per_env_step"] == pytest.approx(0.5, rel=0.2)
    # --config is this tree's settings: the baseline runs its own defaults (batch 64, not 8)
    assert data["baseline"]["batch_size"] != data["default"]["batch_size"] == 8
    worktrees = subprocess.run(["git", "-C", str(ROOT), "worktree", "list"], capture_output=True, text=True)
    assert "baseline-src" not in worktrees.stdout


@pytest.mark.slow
def test_learner_bench_compares_with_a_baseline_commit(tmp_path):
    """``bench/learner.py --baseline REV`` runs REV's bench and this one alternately and reports the
    ratio of their update rates (here REV = HEAD, whose code is this tree's as committed)."""
    args = ["--algos", "hydo-cm", "--seconds", "1", "--threads", "1", "--set", "n_obj=16", "--set", "n_bg=16"]
    data = _run_bench("learner.py", [*args, "--baseline", "HEAD", "--repeats", "1"], tmp_path)
    assert [run["side"] for run in data["runs"]] == ["baseline", "current"]
    assert data["speedup"]["hydo-cm"] == pytest.approx(
        data["current"]["hydo-cm"] / data["baseline"]["hydo-cm"]
    )
    assert data["baseline"]["hydo-cm"] > 0 and data["current"]["hydo-cm"] > 0


@pytest.mark.slow
def test_registration_bench_through_the_object_model(tmp_path):
    """``bench/registration.py --registration model``: the same cases registered through the object's
    mesh (``robot.model_registration``), with the distance error against the truth."""
    data = _run_bench("registration.py", ["--episodes", "2", "--registration", "model"], tmp_path)
    for case in ("start", "near", "turned"):
        s = data[case]["all"]
        assert s["n"] == 2 and s["refused"] == 0
        assert s["distance_error_p90_mm"] < 10 and s["distance_error_over_1cm"] == 0
    # the goal's own fit, one per episode, against the true goal pose
    assert data["goal_fit"]["n"] == 2 and data["goal_fit"]["add_median_mm"] < 10
    assert all(0 <= e["goal_fit_add_m"] < 0.05 for e in data["episodes"])


def test_render_gap_pose_noise_observes_from_a_pose_off_the_true_one():
    """``bench/render_gap.py``'s ``mesh-pose-noise``: with no error it is the training observation bit
    for bit; with 3 mm / 3° the object's points move by millimetres and the flow changes with them."""
    import numpy as np

    sys.path.insert(0, str(ROOT / "bench"))
    from render_gap import observe_from_a_pose_off

    from hydo_cli.envs import make_envs

    def first_obs(sigma_m: float, sigma_deg: float, hooked: bool) -> dict:
        (env,) = make_envs("train", "6d", 0, "mesh", 1)
        if hooked:
            observe_from_a_pose_off(env, np.random.default_rng(0), sigma_m, sigma_deg)
        obs, _ = env.reset(seed=7)
        env.close()
        return obs

    plain = first_obs(0.0, 0.0, False)
    for key, value in first_obs(0.0, 0.0, True).items():
        assert np.array_equal(value, plain[key]), key
    off = first_obs(0.003, 3.0, True)
    shift = np.linalg.norm(off["points"] - plain["points"], axis=-1)
    moved = shift[shift > 0]
    assert len(moved) > 0 and 0.0005 < np.median(moved) < 0.02
    assert not np.array_equal(off["features"], plain["features"])  # the goal flow, from the pose off


def test_curves_window_means(tmp_path):
    """``bench/curves.py --windows``: each seed's mean success over the evaluations inside each window
    of wall-clock minutes (the last window closed), None where a window holds none; bad edges are
    refused in one line."""
    run = tmp_path / "run"
    run.mkdir()
    for name in ("config.json", "metrics.jsonl"):
        (run / name).write_text((OLD_RUN / name).read_text())
    evals = [(5, 0.2), (25, 0.4), (30, 0.5), (59, 0.7), (90, 0.9)]  # (minute, success)
    (run / "eval.jsonl").write_text(
        "".join(
            json.dumps(
                {
                    "env_steps": 100 * i,
                    "updates": 50 * i,
                    "wall_s": 60.0 * m,
                    "success_rate": s,
                    "episodes": 50,
                }
            )
            + "\n"
            for i, (m, s) in enumerate(evals, 1)
        )
    )
    (group,) = _run_bench("curves.py", [str(run), "--windows", "0,30,60,90,150"], tmp_path).values()
    (windows,) = group["windows"]
    assert [(w["mean"], w["evaluations"]) for w in windows] == [
        (pytest.approx(0.3), 2),
        (pytest.approx(0.6), 2),
        (None, 0),
        (pytest.approx(0.9), 1),
    ]
    bad = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "curves.py"), str(run), "--windows", "30,10"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode != 0 and "increasing" in bad.stderr and "Traceback" not in bad.stderr
