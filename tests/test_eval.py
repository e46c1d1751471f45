"""``hydo eval``: several runs, IQM [CI] across them, JSON / Markdown, --compare, --task, bad targets."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hydo_cli.main import app
from hydo_cli.report import aggregate, failure_counts, goal_kind_breakdown, tilt_bands
from hydo_cli.rollout import EpisodeResult
from hydo_cli.tables import compare_rows

runner = CliRunner()


def hydo(*args, cwd=None):
    """The real console entry point in a subprocess (known errors -> one stderr line)."""
    return subprocess.run(
        [sys.executable, "-c", "from hydo_cli.main import main; main()", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


def ep(success, failure="", rejected=0, obj="cube"):
    return EpisodeResult(obj, success, 3, -0.1, 0.01, rejected, failure)


def test_failure_reasons_count_timeouts_with_refused_primitives_twice():
    results = [
        ep(True, rejected=2),  # refused primitives in a success: not a failure
        ep(False, "timeout", rejected=3),
        ep(False, "timeout"),
        ep(False, "object_left_bin", rejected=1),
    ]
    assert failure_counts(results) == {"object_left_bin": 1, "timeout": 2, "primitive_rejected": 2}


def test_goal_kinds_split_moves_from_flips_at_30_degrees():
    def tilted(success, tilt, final, force_stops=0, final_tilt=0.0, split=(None, None)):
        return EpisodeResult(
            "cube",
            success,
            3,
            -0.1,
            final,
            0,
            "" if success else "timeout",
            None,
            0.2,
            tilt,
            force_stops,
            final_tilt,
            final_position_m=split[0],
            final_rotation_m=split[1],
        )

    results = [tilted(True, 0.0, 0.01), tilted(False, 29.0, 0.05), tilted(True, 90.0, 0.02)]
    # one failed flip never turned over (90 deg still left), the other did and ended off the goal
    results += [tilted(False, 180.0, 0.08, 3, final_tilt=2.0), tilted(False, 90.0, 0.12, 1, final_tilt=90.0)]
    kinds = goal_kind_breakdown(results)
    assert kinds["move"]["episodes"] == 2 and kinds["move"]["success_rate"] == 0.5
    assert kinds["flip"]["episodes"] == 3 and kinds["flip"]["success_rate"] == 1 / 3
    assert kinds["flip"]["median_failed_final_distance_m"] == pytest.approx(0.10)
    assert kinds["move"]["mean_start_distance_m"] == pytest.approx(0.2)
    assert kinds["flip_side"]["episodes"] == 2 and kinds["flip_side"]["success_rate"] == 0.5
    assert kinds["flip_over"]["episodes"] == 1 and kinds["flip_over"]["success_rate"] == 0.0
    assert kinds["flip"]["force_stops_failed"] == 2.0 and kinds["flip"]["force_stops_success"] == 0.0
    assert kinds["flip_over"]["force_stops_success"] is None  # no success to average over
    assert kinds["flip"]["failed_wrong_face"] == 0.5 and kinds["flip_side"]["failed_wrong_face"] == 1.0
    assert kinds["move"]["failed_wrong_face"] == 0.0  # the failed move ended on its own face
    assert goal_kind_breakdown(results[:1])["move"]["failed_wrong_face"] is None  # no failures
    assert set(goal_kind_breakdown(results[:1])) == {"move"}  # planar goals: no flip row
    # failures on the goal's face, split into placing and turning; records from before have no split
    assert kinds["flip"]["failed_on_face_position_led"] is None
    assert kinds["move"]["median_failed_on_face_position_m"] is None
    split = [
        tilted(False, 90.0, 0.06, final_tilt=3.0, split=(0.05, 0.02)),  # placing left
        tilted(False, 180.0, 0.05, final_tilt=1.0, split=(0.01, 0.045)),  # turning left
        tilted(False, 90.0, 0.07, final_tilt=5.0, split=(0.06, 0.01)),
        tilted(False, 90.0, 0.20, final_tilt=90.0, split=(0.01, 0.20)),  # never flipped: not on face
    ]
    flip = goal_kind_breakdown(split)["flip"]
    assert flip["failed_on_face"] == 3 and kinds["flip"]["failed_on_face"] == 1
    assert flip["failed_on_face_position_led"] == pytest.approx(2 / 3)
    assert flip["median_failed_on_face_position_m"] == pytest.approx(0.05)
    assert flip["median_failed_on_face_rotation_m"] == pytest.approx(0.02)
    # the same episodes by the goal's tilt band: a band's lower edge belongs to it, 180 to the last
    results += [tilted(True, 30.0, 0.01), tilted(True, 100.0, 0.01), tilted(False, 150.0, 0.09)]
    assert tilt_bands(results) == {
        "0-30": {"episodes": 2, "successes": 1},
        "30-100": {"episodes": 3, "successes": 2},
        "100-150": {"episodes": 1, "successes": 1},
        "150-180": {"episodes": 2, "successes": 0},
    }
    assert tilt_bands(results[:1])["100-150"] == {"episodes": 0, "successes": 0}  # every band has a row


def test_multi_target_eval_writes_json_and_markdown(tmp_path):
    js, md = tmp_path / "out" / "eval.json", tmp_path / "eval.md"
    r = runner.invoke(
        app,
        [
            "eval",
            "heuristic",
            "random",
            "--objects",
            "cube",
            "--episodes",
            "3",
            "--json",
            str(js),
            "--markdown",
            str(md),
        ],
    )
    assert r.exit_code == 0, r.output
    data = json.loads(js.read_text())
    assert [run["target"] for run in data["runs"]] == ["heuristic", "random"]
    for run in data["runs"]:
        from sim.contract import SUCCESS_THRESHOLD_M

        detail = run["episodes_detail"]
        assert run["episodes"] == 3 and len(detail) == 3
        # the rate is the episodes' own, and each episode's success is the contract's threshold
        assert run["success_rate"] == pytest.approx(sum(e["success"] for e in detail) / 3)
        assert all(e["success"] == (e["final_distance"] < SUCCESS_THRESHOLD_M) for e in detail)
        assert run["failures"]["timeout"] == sum(e["failure"] == "timeout" for e in detail)
        assert run["idle_primitives"] == sum(e["idle"] for e in detail)  # pushes that left it in place
        assert run["idle_share"] == pytest.approx(run["idle_primitives"] / sum(e["steps"] for e in detail))
        assert set(run["failures"]) == {"object_left_bin", "timeout", "primitive_rejected"}
        assert set(run["per_object"]) == {"cube"} and run["episodes_per_s"] > 0
    assert data["runs"][0]["stochastic"] is False and data["runs"][1]["stochastic"] is True
    # two methods are never pooled: no IQM across them, one per method (its one run's rate)
    assert data["iqm"] is None and data["aggregate"]["all"] is None
    for run in data["runs"]:
        own = data["aggregate"]["methods"][run["method"]]["all"]
        assert (
            own["iqm"] == pytest.approx(run["success_rate"]) and own["ci_low"] <= own["iqm"] <= own["ci_high"]
        )
        assert own["ci_over"] == "episodes" and "IQM is that run's score" in own["note"]
    text = md.read_text()
    assert "| run | method | success |" in text and "| heuristic |" in text and "| random |" in text
    assert "IQM" in text and not list(tmp_path.glob("**/.*.tmp"))  # atomic writes leave no temp files


def test_compare_lays_out_table_one(tmp_path):
    js, md = tmp_path / "t1.json", tmp_path / "t1.md"
    r = runner.invoke(
        app,
        [
            "eval",
            "random",
            "heuristic",
            "--compare",
            "--episodes",
            "2",
            "--json",
            str(js),
            "--markdown",
            str(md),
        ],
    )
    assert r.exit_code == 0, r.output
    data = json.loads(js.read_text())
    assert data["splits"] == ["unseen-category", "unseen-instance", "train"]
    assert len(data["runs"]) == 6 and {run["objects"] for run in data["runs"]} == set(data["splits"])
    methods = data["aggregate"]["methods"]
    assert list(methods) == ["heuristic", "random"]  # Table I order, not argument order
    for m in methods.values():
        assert set(m["splits"]) == set(data["splits"])
        assert all({"iqm", "ci_low", "ci_high"} <= set(c) for c in m["splits"].values())
    text = md.read_text()
    assert "| Method | Unseen Category | Unseen Instance | Training Objects | Runs |" in text
    table = text.split("| Method |")[1].split("\n\n")[0].splitlines()
    assert table[2].startswith("| heuristic | ") and table[3].startswith("| random | ")
    assert "Table I" in r.output


def test_compare_groups_runs_by_method_in_paper_order():
    def run(target, method, successes, split="train"):
        detail = [{"success": bool(s), "behaviour": None} for s in successes]
        return {"target": target, "method": method, "objects": split, "episodes_detail": detail}

    runs = [run(f"hydo-s{i}", "hydo", [1, 1, 0, i % 2]) for i in range(4)] + [
        run("hacman-s0", "hacman", [0, 0, 1, 0]),
        run("hacman-s1", "hacman", [0, 1, 1, 1]),
    ]
    agg = aggregate(runs, ["train"], seed=0)
    assert list(agg["methods"]) == ["hacman", "hydo"]
    hydo_train = agg["methods"]["hydo"]["splits"]["train"]
    assert hydo_train["ci_over"] == "runs" and hydo_train["iqm"] == pytest.approx(
        0.625
    )  # scores .5 .75 .5 .75
    hacman_train = agg["methods"]["hacman"]["splits"]["train"]
    assert hacman_train["iqm"] == pytest.approx(0.5) and hacman_train["ci_over"] == "episodes"
    header, rows = compare_rows({"task": None, "splits": ["train"], "aggregate": agg})
    assert header == ["Method", "Training Objects", "Runs"]
    assert rows[0][0] == "HACMan" and rows[1][0] == "HyDo" and rows[1][2] == "4"
    # two seeds: the episode interval, then the one across seeds; four: the run bootstrap alone
    assert rows[0][1].startswith("0.500 [") and "; seeds [" in rows[0][1] and "seeds" not in rows[1][1]


def test_task_eval_reports_behaviour_entropy(tmp_path):
    js = tmp_path / "line.json"
    r = runner.invoke(app, ["eval", "heuristic", "--task", "push-line", "--episodes", "3", "--json", str(js)])
    assert r.exit_code == 0, r.output
    data = json.loads(js.read_text())
    run = data["runs"][0]
    assert data["task"]["name"] == "push-line" and data["task"]["n_behaviours"] == 24
    assert run["behaviour_entropy"] == 0.0 and run["behaviour_counts"] == {"18": 3}  # one behaviour
    assert data["aggregate"]["behaviour_entropy"]["iqm"] == 0.0
    assert "entropy" in r.output


def bad_targets(tmp_path):
    (tmp_path / "corrupt.pt").write_bytes(b"not a checkpoint")
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("hello")
    model = tmp_path / "model"
    model.mkdir()
    keys = "format obs_contract_version algo n_obj n_bg feature_dim denoise_steps noise_per_point"
    keys += " noise_schedule q_reduction stochastic training_command sha256"
    manifest = dict.fromkeys(keys.split(), 0) | {"format": "hydo-onnx/1", "obs_contract_version": 999}
    (model / "manifest.json").write_text(json.dumps(manifest))


def test_goals_default_to_the_mode_the_runs_were_trained_on(tmp_path):
    """A 6D model is scored on 6D goals without --goals; --goals overrides; mixed modes must choose."""
    models = Path(__file__).resolve().parents[1] / "models"
    six_d, planar = str(models / "hydo-cm-6d"), str(models / "hydo-cm-planar")

    def episodes(*args):
        js = tmp_path / "eval.json"
        r = runner.invoke(app, ["eval", *args, "--objects", "wedge_00", "--episodes", "3", "--json", str(js)])
        assert r.exit_code == 0, r.output
        data = json.loads(js.read_text())
        return data["goals"], [
            (e["start_distance"], e["goal_tilt_deg"]) for e in data["runs"][0]["episodes_detail"]
        ]

    default_mode, default_eps = episodes(six_d)
    assert default_mode == "6d" and default_eps == episodes(six_d, "--goals", "6d")[1]
    planar_mode, planar_eps = episodes(six_d, "--goals", "planar")
    assert planar_mode == "planar" and planar_eps != default_eps  # the flag wins over the manifest
    assert all(tilt < 1 for _, tilt in planar_eps) and any(tilt > 30 for _, tilt in default_eps)  # degrees
    assert episodes("heuristic")[0] == "planar" and episodes(planar)[0] == "planar"
    mixed = hydo("eval", six_d, planar, "--objects", "wedge_00", "--episodes", "1")
    assert mixed.returncode == 1 and "different --goals" in mixed.stderr, mixed.stderr
    assert len(mixed.stderr.strip().splitlines()) == 1 and "Traceback" not in mixed.stderr


@pytest.mark.parametrize(
    "targets, message",
    [
        (["corrupt.pt"], "corrupt"),
        (["notes"], "neither checkpoint.pt"),
        (["model"], "observation contract v999"),
        (["heuristic", "no/such/run"], "no/such/run"),  # every target loads before any episode runs
    ],
)
def test_bad_target_is_one_line_and_exit_1(targets, message, tmp_path):
    bad_targets(tmp_path)
    r = hydo("eval", *targets, "--objects", "cube", "--episodes", "1", cwd=tmp_path)
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "success" not in r.stdout  # nothing was evaluated


@pytest.mark.parametrize(
    "args, message",
    [
        (["heuristic", "heuristic"], "given twice"),
        (["heuristic", "--compare", "--objects", "cube"], "drop --objects"),
        (["heuristic", "--task", "push-line", "--goals", "6d"], "drop --objects/--goals/--clutter"),
        (["heuristic", "random", "--video", "v.mp4"], "one TARGET"),
    ],
)
def test_contradictory_flags_are_refused(args, message, monkeypatch, capsys):
    from hydo_cli.main import main

    monkeypatch.setattr(sys, "argv", ["hydo", "eval", *args])
    with pytest.raises(SystemExit) as e:
        main()
    err = capsys.readouterr().err
    assert e.value.code == 1 and message in err and len(err.strip().splitlines()) == 1


def test_recorded_evaluations_join_table_one_without_rerunning(tmp_path):
    """A `hydo eval --json` report (plain or gzip) is a TARGET: its runs join the aggregate as they
    were recorded, on the same episodes, and equal a live evaluation of the same runs."""
    import gzip

    common = ["--compare", "--episodes", "2", "--seed", "3", "--goals", "planar"]
    rec_h, rec_r = tmp_path / "h.json", tmp_path / "r.json"
    assert runner.invoke(app, ["eval", "heuristic", *common, "--json", str(rec_h)]).exit_code == 0
    assert runner.invoke(app, ["eval", "random", *common, "--json", str(rec_r)]).exit_code == 0
    gz = tmp_path / "r.json.gz"  # --json FILE.gz writes it compressed
    assert runner.invoke(app, ["eval", "random", *common, "--json", str(gz)]).exit_code == 0
    zipped, plain = json.loads(gzip.decompress(gz.read_bytes())), json.loads(rec_r.read_text())
    assert [r["episodes_detail"] for r in zipped["runs"]] == [r["episodes_detail"] for r in plain["runs"]]
    live, mixed = tmp_path / "live.json", tmp_path / "mixed.json"
    assert runner.invoke(app, ["eval", "heuristic", "random", *common, "--json", str(live)]).exit_code == 0
    md = tmp_path / "mixed.md"
    r = runner.invoke(
        app, ["eval", str(rec_h), str(gz), *common, "--json", str(mixed), "--markdown", str(md)]
    )
    assert r.exit_code == 0, r.output
    assert f"| heuristic (recorded in {rec_h}) | heuristic | unseen-category |" in md.read_text()
    a, b = json.loads(live.read_text()), json.loads(mixed.read_text())
    assert [(x["target"], x["objects"]) for x in a["runs"]] == [
        (x["target"], x["objects"]) for x in b["runs"]
    ]
    for x, y in zip(a["runs"], b["runs"], strict=True):
        assert x["episodes_detail"] == y["episodes_detail"]  # the same episodes, the same play
    assert a["aggregate"]["methods"] == b["aggregate"]["methods"]
    assert {x["recorded"] for x in b["runs"]} == {str(rec_h), str(gz)} and b["episodes_per_s"] is None
    # a record joins live runs of other methods (the same run twice: test_a_bad_record_...)
    r = runner.invoke(app, ["eval", str(rec_h), "random", *common])
    assert r.exit_code == 0 and "1 recorded evaluations" in r.output, r.output


REC = ["--episodes", "2", "--seed", "3", "--goals", "planar"]  # the record's episodes


@pytest.fixture(scope="module")
def records(tmp_path_factory) -> dict[str, Path]:
    """Two real records, made once: heuristic on every split (``compare``) and on the cube alone."""
    out = {}
    for name, split in (("compare", ["--compare"]), ("cube", ["--objects", "cube"])):
        out[name] = tmp_path_factory.mktemp("records") / f"{name}.json"
        assert hydo("eval", "heuristic", *split, *REC, "--json", str(out[name])).returncode == 0
    return out


@pytest.mark.parametrize(
    "make, cli, message",
    [
        (None, ["--objects", "cube", *REC], "not found"),
        ("{not json", ["--objects", "cube", *REC], "not a readable"),
        ('{"runs": []}', ["--objects", "cube", *REC], "it lacks goals"),
        (
            "compare",
            ["--compare", "--episodes", "2", "--seed", "4"],
            "--seed 3, this evaluation with --seed 4",
        ),
        ("compare", ["--compare", "--episodes", "3", "--seed", "3"], "--episodes 2, this evaluation with"),
        (
            "compare",
            ["--compare", *REC[:4], "--goals", "6d"],
            "--goals planar, this evaluation with --goals 6d",
        ),
        (
            "compare",
            ["--compare", *REC, "--contacts", "hacman"],
            "--contacts hydo, this evaluation with --contacts hacman",
        ),
        ("compare", ["heuristic", "--compare", *REC], "give it once"),
        ("cube", ["--compare", *REC], "holds no run on unseen-category"),
    ],
)
def test_a_bad_record_is_one_line_and_exit_1(make, cli, message, records, tmp_path):
    """Records made on other episodes, of another split, of a run given twice, or not records at all."""
    path = records[make] if make in records else tmp_path / "rec.json"
    if make is not None and make not in records:
        path.write_text(make)
    r = hydo("eval", str(path), *cli, cwd=tmp_path)
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_record_made_before_contacts_existed_reads_as_the_scenes_own():
    """Records written before ``--contacts`` existed were played in hydo's contact model."""
    import gzip

    from hydo_cli.records import load_record

    path = Path(__file__).resolve().parents[1] / "docs" / "table1-6d" / "hacman-s0.json.gz"
    assert "contacts" not in json.loads(gzip.decompress(path.read_bytes()))
    assert load_record(str(path))["contacts"] == "hydo"


def test_eval_plays_in_the_contacts_a_run_was_trained_in_unless_told(tmp_path):
    """``hydo eval`` plays in the contact model the runs were trained in (hydo's for baselines alone);
    ``--contacts`` overrides it with a one-line note saying how to match, and runs trained in different
    models need it."""
    import shutil

    from models.checkpoint import load_checkpoint, save_checkpoint

    data = Path(__file__).resolve().parent / "data" / "old-run-v0"
    run, other = tmp_path / "run", tmp_path / "other"
    shutil.copytree(data, run)
    shutil.copytree(data, other)  # made before contacts existed: the scene's own
    ckpt = load_checkpoint(run / "checkpoint.pt")
    ckpt["config"] = json.dumps({**json.loads(ckpt["config"]), "contacts": "hacman"})
    save_checkpoint(run / "checkpoint.pt", ckpt)
    args = ["eval", str(run), "--objects", "cube", "--episodes", "1", "--json"]
    r = hydo(*args, str(tmp_path / "a.json"), cwd=tmp_path)
    assert r.returncode == 0 and "trained with contacts" not in r.stderr, r.stderr
    assert json.loads((tmp_path / "a.json").read_text())["contacts"] == "hacman"
    r = hydo(*args, str(tmp_path / "b.json"), "--contacts", "hydo", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "was trained with contacts hacman" in r.stderr and "--contacts hacman to match" in r.stderr
    assert json.loads((tmp_path / "b.json").read_text())["contacts"] == "hydo"
    r = hydo("eval", str(run), str(other), "--objects", "cube", "--episodes", "1", cwd=tmp_path)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert "trained with different --contacts" in r.stderr and "(hacman)" in r.stderr and "(hydo)" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_run_reports_its_training_budget_and_table_one_shows_it():
    """A trained run's eval report carries its budget (``training``): Table I "at the same budget" is
    read off the records, and one method's runs trained with other learner settings are pointed out."""
    from hydo_cli.policies import load_policy
    from hydo_cli.tables import budget_rows, learner_notes, markdown_report

    old_run = Path(__file__).parent / "data" / "old-run-v0"  # 120 env steps, batch 8, K 2, no limit
    budget = load_policy(str(old_run), seed=0).training
    assert budget["env_steps"] == 120 and budget["max_minutes"] == 0 and budget["objects"] == "cube"
    assert budget["sample_gradients"] == budget["updates"] * 8 and budget["updates"] > 0
    assert budget["learner"] == {
        "batch_size": 8,
        "updates_per_step": 0.5,
        "denoise_steps": 2,
        "policy_delay": 1,
    }
    assert load_policy("heuristic").training is None

    def run(target, method, training, split="train"):
        detail = [{"success": True, "behaviour": None}]
        return {
            "target": target,
            "method": method,
            "objects": split,
            "episodes_detail": detail,
            "training": training,
        }

    other = {**budget, "learner": {**budget["learner"], "denoise_steps": 5}}
    runs = [
        run("a", "hydo-cm", budget),
        run("a", "hydo-cm", budget, "unseen-instance"),  # one row per run, not per split
        run("b", "hydo-cm", other),
        run("c", "hacman", budget),
        run("d", "hacman", "150 min"),  # a record from elsewhere: malformed, left out
        run("e", "hacman", None),  # a record from before the key
    ]
    report = {"runs": runs}
    header, rows = budget_rows(report)
    assert [r[0] for r in rows] == ["a", "b", "c"] and header[2] == "minutes"
    assert rows[0][3] == "120" and rows[0][6] == "K 2, batch 8, UTD 0.5, actor every 1"
    (note,) = learner_notes(report)
    assert note.startswith("note: HyDo + CM's runs were trained with 2 different learners") and "K 5" in note
    assert budget_rows({"runs": [run("e", "hacman", None)]})[1] == []
    # the Markdown report lays the budgets out under the runs
    agg = aggregate(runs[:1], ["train"], seed=0)
    full = {"command": "hydo eval a", "compare": False, "task": None, "splits": ["train"], "goals": "planar"}
    full |= {"clutter": 0, "obs": "mesh", "episodes": 1, "seed": 0, "aggregate": agg}
    one = {
        **runs[0],
        "description": "a",
        "stochastic": True,
        "episodes_per_s": 1.0,
        "failures": failure_counts([]),
    }
    one |= {
        "success_rate": 1.0,
        "episodes": 1,
        "mean_steps_to_success": 1.0,
        "rejected_primitives": 0,
        "per_object": {},
    }
    assert "## Training budgets" in markdown_report({**full, "runs": [one]})


def test_shards_of_an_evaluation_play_the_same_episodes_as_the_whole():
    # training's evaluation is shared by its workers: worker r plays episodes r, r + world, ... of
    # the same seeded set, so two shards together are the whole set, episode for episode
    from hydo_cli.envs import make_envs
    from hydo_cli.rollout import baseline_policy, run_episodes

    envs = make_envs("train", "6d", 0, "mesh", 2, 32, 32)

    def play(shard):
        return run_episodes(envs, baseline_policy("random", 0), 5, seed=4, shard=shard)

    def start(r):
        return (r.object, round(r.start_distance, 9), round(r.goal_tilt_deg, 6))

    whole = [start(r) for r in play((0, 1))]
    assert len(set(whole)) > 1  # different objects and goals, so a wrong index would show
    assert [start(r) for r in play((0, 2))] == whole[0::2]
    assert [start(r) for r in play((1, 2))] == whole[1::2]
    assert [start(r) for r in play((3, 4))] == [whole[3]]  # of 5 episodes, only episode 3
    with pytest.raises(ValueError, match="shard"):
        play((2, 2))
