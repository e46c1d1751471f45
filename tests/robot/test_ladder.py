"""The sim → twin ladder and what it rests on: twin episodes that are ``hydo eval``'s episodes, the
twin's true-pose perception, registrations that say when a symmetric object makes them ambiguous,
and a deploy verdict that never counts an ambiguous registration as a success."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from robot.errors import InputError, RegistrationError
from robot.loop import DeployConfig, Deployment, resolve_registration
from robot.registration import Registration, register
from robot.session_log import read_log
from sim.contract import SUCCESS_THRESHOLD_M, pose_matrix, transform_points
from sim.goals import episode_seed


def box_cloud(size, spacing=0.004) -> np.ndarray:
    """Points (N, 3) on the top and the four sides of a box of ``size`` (x, y, z) resting on z = 0."""
    sx, sy, sz = size
    xs, ys, zs = (np.arange(-s / 2, s / 2 + 1e-9, spacing) for s in (sx, sy, sz))
    zs = zs + sz / 2
    top = np.stack(np.meshgrid(xs, ys, [sz], indexing="ij"), -1).reshape(-1, 3)
    sides = [np.stack(np.meshgrid([x], ys, zs, indexing="ij"), -1).reshape(-1, 3) for x in (-sx / 2, sx / 2)]
    sides += [np.stack(np.meshgrid(xs, [y], zs, indexing="ij"), -1).reshape(-1, 3) for y in (-sy / 2, sy / 2)]
    return np.concatenate([top, *sides])


def moved(points, dx, yaw=0.0):
    T = pose_matrix(np.array([dx, 0.0, 0.0]), np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]))
    return transform_points(T, points)


def test_registration_verdict_up_to_symmetry_and_ambiguous_when_the_views_differ():
    """A 6 x 6 cm cube 1.5 cm from its goal fits it turned by 90, 180 and 270 degrees as well: the flow
    points to the nearest fit, and since both clouds show the same cube, the other fits are its own
    symmetry: a success (goals are reached up to symmetry). A box whose end block is hidden in the
    current view but seen in the goal's fits the goal both ways round, one within 3 cm and one not,
    and the goal shows surface the current cloud lacks: ``ambiguous``, never a success. With no
    symmetry and both views alike (the box with its block in both), a plain success."""
    rng = np.random.default_rng(0)
    cube = box_cloud((0.06, 0.06, 0.06))
    reg = register(moved(cube, 0.015) + rng.normal(0, 0.0005, cube.shape), cube, "planar")
    assert abs(reg.distance - 0.015) < 0.003 and reg.distance < min(reg.alternatives)
    assert reg.ambiguous and max(reg.alternatives) > SUCCESS_THRESHOLD_M and reg.goal_coverage > 0.9
    assert reg.verdict(SUCCESS_THRESHOLD_M) == "success"

    body = box_cloud((0.12, 0.05, 0.03))
    block = box_cloud((0.04, 0.05, 0.03)) + [0.04, 0, 0.03]
    shape = np.concatenate([body, block])
    reg = register(moved(body, 0.015) + rng.normal(0, 0.0005, body.shape), shape, "planar")
    assert reg.goal_coverage < 0.85 and reg.verdict(SUCCESS_THRESHOLD_M) == "ambiguous"

    reg = register(moved(shape, 0.015, 0.1) + rng.normal(0, 0.0005, shape.shape), shape, "planar")
    assert reg.verdict(SUCCESS_THRESHOLD_M) == "success" and not reg.ambiguous
    # the verdict: (distance, alternatives, goal coverage, inlier fraction)
    verdict = [
        Registration(np.eye(4), 0.001, inl, d, 0.0, alt, cov).verdict(SUCCESS_THRESHOLD_M)
        for d, alt, cov, inl in (
            (0.01, (0.02,), 0.97, 1.0),
            (0.01, (0.05,), 0.97, 1.0),
            (0.01, (0.05,), 0.8, 1.0),
            (0.05, (0.06,), 0.95, 1.0),
            (0.05, (0.01,), 0.95, 1.0),  # the nearer fit is the object's own symmetry: a failure
            (0.05, (0.01,), 0.8, 1.0),  # a nearer fit the current view cannot rule out
            # under 3 cm, but the views match less closely than an object at its goal: not claimed
            (0.01, (0.02,), 0.5, 1.0),
            (0.01, (0.05,), 0.93, 1.0),  # covered enough to call the far fit a symmetry, not a success
            (0.01, (), 1.0, 0.85),  # a tenth of the points the goal shows have no goal point near them
        )
    ]
    assert verdict == [
        "success",
        "success",
        "ambiguous",
        "failure",
        "failure",
        "ambiguous",
        "uncertain",
        "uncertain",
        "uncertain",
    ]
    # registered to the object's model, an alternative is never the object's symmetry: one past the
    # threshold makes the reading ambiguous however well the goal cloud is covered
    near = dict(
        T=np.eye(4), rmse=0.001, inlier_fraction=1.0, distance=0.02, seconds=0.0, alternatives=(0.06,)
    )
    assert Registration(**near, goal_coverage=0.96).verdict(SUCCESS_THRESHOLD_M, 0.003) == "success"
    assert (
        Registration(**near, goal_coverage=0.96, folded=True).verdict(SUCCESS_THRESHOLD_M, 0.003)
        == "ambiguous"
    )
    # within the success margin under the threshold: not yet a success
    assert Registration(np.eye(4), 0.001, 1.0, 0.027, 0.0).verdict(SUCCESS_THRESHOLD_M, 0.005) == "uncertain"


def test_an_ambiguous_registration_is_acted_on_again_and_never_a_success(tiny_model, tmp_path, monkeypatch):
    """The deploy loop does not stop on it: the policy acts again (the push changes the view) up to
    the step limit, where the episode is reported as ambiguous (summary and table), not a success."""
    from robot import loop
    from robot.report import summary_lines

    real_register = loop.register_checked

    def ambiguous(*args):
        reg, widened = real_register(*args)
        return Registration(reg.T, reg.rmse, reg.inlier_fraction, 0.01, reg.seconds, (0.06,), 0.5), widened

    monkeypatch.setattr(loop, "register_checked", ambiguous)
    dep = Deployment.prepare(
        DeployConfig(robot="sim", model=tiny_model, episodes=1, max_steps=2, log_dir=tmp_path / "s")
    )
    res = dep.run()
    (ep,) = res.episodes
    assert not ep.success and ep.cause == "ambiguous" and ep.steps == 2 and res.commands_sent > 0
    assert res.summary()["ambiguous_episodes"] == 1 and res.summary()["success_rate"] == 0.0
    assert ("ambiguous (not counted as success)", "1") in summary_lines(res)


def _twin_session(tiny_model, folder, **cfg):
    """Two twin episodes of seed 5, at most two primitives each, under ``cfg``; the prepared
    deployment and its result."""
    dep = Deployment.prepare(
        DeployConfig(robot="sim", model=tiny_model, episodes=2, max_steps=2, seed=5, log_dir=folder, **cfg)
    )
    return dep, dep.run()


def test_true_perception_observes_the_twin_like_the_training_env(tiny_model, tmp_path):
    """``perception="true"``: the exact transform to the true goal (IoU 1), the true distance
    as the loop's distance, so the loop's verdict is the true one; twin episode ``i`` of seed ``s``
    is ``hydo eval --seed s``'s episode ``i`` (same object, start and goal, in the cell's bin)."""
    from sim.env import BinEnv

    dep, res = _twin_session(tiny_model, tmp_path / "s", perception="true")
    s = res.summary()
    # (ADD-S against the exact goal: the nearest symmetric goal is a turn the surface maps onto itself)
    assert s["mean_iou"] == pytest.approx(1.0) and s["mean_registration_error_m"] < 0.001
    assert s["flow_off_1cm"] == 0.0  # the true flow, not only its size
    for e in res.episodes:
        assert e.success == e.true_success and e.distance == pytest.approx(e.true_distance, abs=1e-6)
    env = BinEnv(objects="cube", goals="planar")
    starts = [e for e in read_log(tmp_path / "s") if e["event"] == "twin_episode"]
    for i, logged in enumerate(starts):
        env.reset(seed=episode_seed(5, i))
        goal = np.array(logged["goal"])[:3, 3] - dep.cell.bin_center
        assert np.linalg.norm(goal - env.goal_pose[0]) < 0.005  # the same goal, settled in the twin
    env.close()


def test_cameras_true_pose_perception_observes_through_the_cameras_and_flows_by_the_truth(
    tiny_model, tmp_path
):
    """``perception="cameras-true-pose"`` (the ladder's ``twin-cameras`` rung): the segmented camera
    cloud, not the mesh samples (IoU under 1), with the exact transform to the true goal in place of
    registration: the loop's distance is the true one, so its verdict is the true one."""
    _, res = _twin_session(tiny_model, tmp_path / "s", perception="cameras-true-pose")
    s = res.summary()
    assert s["mean_iou"] < 0.999 and s["mean_registration_error_m"] < 0.001
    for e in res.episodes:
        assert e.success == e.true_success and e.distance == pytest.approx(e.true_distance, abs=1e-6)
    observed = [e for e in read_log(tmp_path / "s") if e["event"] == "observation"]
    assert observed and all(e["registration"]["rmse_m"] == 0.0 for e in observed)
    assert not any(e["event"] == "registration_widened" for e in read_log(tmp_path / "s"))


def _cube_obj(path, size: float = 0.06):
    """A ``size`` m cube as an OBJ file (the twin's ``cube`` object), outward-wound."""
    v = [(x, y, z) for x in (0, size) for y in (0, size) for z in (0, size)]
    quads = ((1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4))
    faces = [f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))]
    path.write_text(
        "".join(f"v {x} {y} {z}\n" for x, y, z in v) + "".join(f"f {a} {b} {c}\n" for a, b, c in faces)
    )
    return path


@pytest.mark.parametrize("mesh", [False, True], ids=["twin-object", "object-mesh"])
def test_model_registration_in_the_twin_reads_the_true_distance(tiny_model, tmp_path, mesh):
    """``registration="model"`` in the twin: the model is the episode's object, or the user's
    ``object_mesh`` as on a cell (here an OBJ of the same cube, in its own frame); every step's
    registration reads the true distance to within a few millimetres."""
    mesh_file = _cube_obj(tmp_path / "cube.obj") if mesh else None
    dep, _ = _twin_session(tiny_model, tmp_path / "s", registration="model", object_mesh=mesh_file)
    assert (dep.object_model is not None) == mesh
    observed = [e for e in read_log(tmp_path / "s") if e["event"] == "observation"]
    assert observed
    for e in observed:
        assert abs(e["registration"]["distance_m"] - e["true_distance_m"]) < 0.005
        assert e["registration_error_m"] < 0.008  # ADD-S: as close as view registration gets (2-5 mm)


def test_auto_registration_is_the_mesh_for_6d_goals_where_the_mesh_is_known(
    tiny_model, tiny_model_6d, tmp_path
):
    """``registration="auto"`` (the default): in the twin a 6D-goal policy registers to the episode's
    mesh and a planar one view to view; the session records the choice. On a cell the mesh is known
    only from ``object_mesh``; an explicit choice is kept."""
    for model, want in ((tiny_model, "views"), (tiny_model_6d, "model")):
        dep = Deployment.prepare(DeployConfig(robot="sim", model=model, log_dir=tmp_path / want))
        assert dep.cfg.registration == want and dep.cfg.resolved_observe() == (
            "model" if want == "model" else "cloud"
        )
        assert json.loads((tmp_path / want / "session.json").read_text())["config"]["registration"] == want
    cell = dict(robot="panda", model=tiny_model_6d, goal_offset=(0.1, 0.0, 0.0))
    assert resolve_registration(DeployConfig(**cell), "6d") == "views"
    assert resolve_registration(DeployConfig(**cell, object_mesh=tmp_path / "m.obj"), "6d") == "model"
    assert resolve_registration(DeployConfig(**cell, object_mesh=tmp_path / "m.obj"), "planar") == "model"
    assert (
        resolve_registration(DeployConfig(robot="sim", model=tiny_model_6d, registration="views"), "6d")
        == "views"
    )


def test_a_6d_policy_on_a_cell_without_a_mesh_is_told_in_one_line(tiny_model, tiny_model_6d):
    """On a cell, ``auto`` without ``object_mesh`` falls back to views; for a 6D policy that costs the
    goals that show another face, so ``prepare`` says so (once, before any other check) and names the
    flag. A planar policy gets no note."""
    for model, notes in ((tiny_model_6d, 1), (tiny_model, 0)):
        lines: list[str] = []
        # no goal: refused right after the registration choice, before any device would open
        with pytest.raises(RegistrationError, match="needs a goal"):
            Deployment.prepare(DeployConfig(robot="panda", model=model), printer=lines.append)
        assert len(lines) == notes
        assert all(line.startswith("registration: views") and "--object-mesh" in line for line in lines)


def test_a_policy_trained_in_another_contact_model_is_told_in_one_line(tiny_model, tmp_path):
    """A manifest whose ``contacts`` is not the scene's own (HACMan's, say) gets one note before any
    device opens, on the twin and on a cell: the object keeps its own physics. The scene's own, or
    a manifest from before the key, gets none."""
    hacman = tmp_path / "hacman"
    shutil.copytree(tiny_model, hacman)
    manifest = json.loads((hacman / "manifest.json").read_text())
    manifest["contacts"] = "hacman"
    (hacman / "manifest.json").write_text(json.dumps(manifest))
    older = tmp_path / "older"
    shutil.copytree(tiny_model, older)
    del manifest["contacts"]
    (older / "manifest.json").write_text(json.dumps(manifest))
    for model, robot, want in (
        (hacman, "sim", "the twin's object keeps"),
        (hacman, "panda", "the cell's objects have"),
        (tiny_model, "panda", None),
        (older, "panda", None),
    ):
        lines: list[str] = []
        cfg = DeployConfig(robot=robot, model=model, log_dir=tmp_path / "logs" / f"{model.name}-{robot}")
        if robot == "sim":
            Deployment.prepare(cfg, printer=lines.append)
        else:  # no goal: refused after the notes, before any device would open
            with pytest.raises(RegistrationError, match="needs a goal"):
                Deployment.prepare(cfg, printer=lines.append)
        notes = [line for line in lines if line.startswith("contacts:")]
        if want is None:
            assert notes == [], (model, lines)
        else:
            assert len(notes) == 1 and "hacman" in notes[0] and want in notes[0], lines


@pytest.mark.parametrize("observe", ["model", "cloud"])
def test_model_registration_observes_the_mesh_at_the_fitted_pose(tiny_model, tmp_path, observe):
    """``observe="model"`` (the default with model registration): the policy observes the cube's mesh
    samples and normals at the fitted pose, as training does, so every observed normal is one of the
    cube's six face normals (pairwise dot products exactly 0 or ±1); ``observe="cloud"`` keeps the
    cameras' points and their PCA normals, which are not."""
    _twin_session(tiny_model, tmp_path / "s", registration="model", observe=observe)
    steps = [np.load(f) for f in sorted((tmp_path / "s" / "steps").glob("*.npz"))]
    acted = [s for s in steps if "points" in s.files]
    assert acted
    for s in acted:
        n = s["obj_normals"].astype(np.float64)
        dots = n @ n.T
        face_normals = bool(np.all(np.abs(dots - np.round(dots)) < 1e-3))
        assert face_normals == (observe == "model")


def test_a_twin_episode_does_not_depend_on_how_long_the_one_before_ran(tiny_model, tmp_path):
    """Episode 1 sees the same clouds whether episode 0 ran one step or three: each twin episode's
    depth noise and samples are drawn from (seed, episode), so two code versions that end episode 0
    differently still compare episode 1 to episode 1."""

    def episode_1(max_steps: int, folder: str) -> list:
        cfg = DeployConfig(
            robot="sim", model=tiny_model, episodes=2, max_steps=max_steps, seed=3, log_dir=tmp_path / folder
        )
        Deployment.prepare(cfg).run()
        events = read_log(tmp_path / folder)
        return [
            (e["n_object_points"], e["registration"]["distance_m"])
            for e in events
            if e["event"] == "observation" and e["episode"] == 1 and e["step"] == 0
        ]

    first, second = episode_1(1, "a"), episode_1(3, "b")
    assert first and first == second


def test_a_twin_session_from_episode_k_plays_what_a_session_from_0_plays_there(tiny_model, tmp_path):
    """Episodes 1 and 2 of seed 3 end the same (object, steps, final distance to the bit) in a session
    of episodes 0-2 and in one that starts at episode 1: the twin's simulation state is fresh each
    episode (the solver's warm start carried over before), so the ladder can split a rung's episodes
    over processes. ``first_episode`` is for the twin's sampled episodes only."""

    def episodes(first: int, n: int, folder: str) -> list:
        cfg = DeployConfig(
            robot="sim",
            model=tiny_model,
            episodes=n,
            first_episode=first,
            max_steps=2,
            seed=3,
            perception="true",
            log_dir=tmp_path / folder,
        )
        res = Deployment.prepare(cfg).run()
        started = [e["episode"] for e in read_log(tmp_path / folder) if e["event"] == "episode_start"]
        assert started == list(range(first, first + n))
        return [(e.object, e.steps, e.true_distance) for e in res.episodes]

    whole, piece = episodes(0, 3, "whole"), episodes(1, 2, "piece")
    assert len(whole) == 3 and whole[1:] == piece
    with pytest.raises(ValueError, match="first_episode"):
        Deployment.prepare(
            DeployConfig(robot="panda", model=tiny_model, first_episode=1, log_dir=tmp_path / "c")
        )


def test_a_rung_split_into_pieces_is_merged_back_in_episode_order():
    from hydo_cli.ladder import LadderEpisode, RungResult, merge_pieces, twin_pieces

    assert twin_pieces(100, 2) == [(0, 50), (50, 50)]
    assert twin_pieces(5, 3) == [(0, 2), (2, 2), (4, 1)] and twin_pieces(1, 4) == [(0, 1)]

    def piece(objects, adds, n_reg, refused):
        eps = [
            LadderEpisode(o, o == "cube", 0.01, 3, "success" if o == "cube" else "near_miss") for o in objects
        ]
        return RungResult(
            "twin", "d", eps, force_stops=2, reflexes=1, mean_registration_adds_m=adds, n_registrations=n_reg,
            seconds=10.0, extra={"registration": "model", "steps_refused_by_kind": refused},
        )  # fmt: skip

    merged = merge_pieces(
        [piece(["cube", "mug"], 0.004, 3, {"PlanError": 1}), piece(["wedge"], 0.008, 1, {})]
    )
    assert [e.object for e in merged.episodes] == ["cube", "mug", "wedge"]
    assert (merged.force_stops, merged.reflexes, merged.seconds, merged.n_registrations) == (4, 2, 20.0, 4)
    assert merged.mean_registration_adds_m == pytest.approx(0.005)  # (3 × 4 + 1 × 8) / 4 mm
    assert merged.extra == {"registration": "model", "steps_refused_by_kind": {"PlanError": 1}, "pieces": 2}
    assert merged.summary()["success_rate"] == pytest.approx(1 / 3)


@pytest.mark.parametrize(("robot", "perception"), [("panda", "true"), ("sim", "cameras-true-pose")])
def test_true_poses_exist_only_in_the_twin_with_its_sampled_goals(tiny_model, tmp_path, robot, perception):
    cfg = DeployConfig(
        robot=robot, model=tiny_model, perception=perception, goal_offset=(0.1, 0, 0), log_dir=tmp_path / "a"
    )
    with pytest.raises(InputError, match="only in the twin"):
        Deployment.prepare(cfg)
    with pytest.raises(ValueError, match="perception"):
        Deployment.prepare(
            DeployConfig(robot="sim", model=tiny_model, perception="oracle", log_dir=tmp_path / "b")
        )


def test_ladder_command_runs_the_same_episodes_on_each_rung(tiny_model, tmp_path):
    """``hydo deploy ladder``: a table, ladder.json with each rung's success, causes and the episodes
    lost and gained against the rung above, on the same objects in the same order; with two jobs
    the twin rung's episodes run in two twin sessions."""
    from typer.testing import CliRunner

    from hydo_cli.main import app

    out = tmp_path / "ladder"
    r = CliRunner().invoke(
        app,
        [
            "deploy",
            "ladder",
            "--model",
            str(tiny_model),
            "--episodes",
            "2",
            "--rungs",
            "twin-true,env",
            "--jobs",
            "2",
            "--log",
            str(out),
            "--json",
            str(tmp_path / "l.json"),
            "--env-draws",
            "3",
        ],
    )
    assert r.exit_code == 0, r.output
    assert "sim -> twin ladder" in r.output
    assert "env over 3 draws of the policy's sampling" in " ".join(r.output.split())
    doc = json.loads((out / "ladder.json").read_text())
    assert doc == json.loads((tmp_path / "l.json").read_text())
    env, twin = doc["rungs"]
    assert (env["rung"], twin["rung"]) == ("env", "twin-true")  # ladder order, whatever was asked
    assert env["episodes"] == twin["episodes"] == 2 and "lost_vs_previous" in twin
    # the env rung's spread: its own draw first, then two more of the policy's sampling
    assert len(env["policy_draws"]) == 3 and env["policy_draws"][0] == env["success_rate"]
    assert env["policy_draws_mean"] == np.mean(env["policy_draws"]) and "policy_draws" not in twin
    for rung in doc["rungs"]:
        failed = sum(not e["success"] for e in doc["episodes"][rung["rung"]])
        assert sum(rung["causes"].values()) == failed
    # two processes: the twin rung's episodes in two pieces, one twin session each, merged back
    pieces = [
        json.loads((out / "twin-true" / p / "summary.json").read_text()) for p in ("e000-000", "e001-001")
    ]
    assert [p["episodes"] for p in pieces] == [1, 1] and twin["pieces"] == 2
    objects = [[e["object"] for e in doc["episodes"][k]] for k in ("env", "twin-true")]
    assert objects[0] == objects[1]

    bad = CliRunner().invoke(app, ["deploy", "ladder", "--model", str(tiny_model), "--rungs", "sim"])
    said = " ".join(bad.output.replace("│", " ").split())  # the message as one line, out of its box
    assert bad.exit_code == 2 and "rungs are env, env-render, twin-true, twin-cameras, twin" in said


def test_the_summary_counts_the_flows_off_the_true_one(tmp_path):
    """A twin step whose flow transform moves the object's surface 1 cm or more from where the true
    flow does (ADD) counts, whatever distance it reads; steps without the truth do not."""
    from robot.report import SessionResult, StepRecord, summary_lines

    res = SessionResult(tmp_path)
    res.steps = [
        StepRecord(0, i, 0.1, 0.0, 1.0, 100, registration_add=add)
        for i, add in enumerate((0.002, 0.015, None, 0.03))
    ]
    assert res.summary()["flow_off_1cm"] == pytest.approx(2 / 3)
    assert ("flows off the true one by 1 cm+ (ADD, twin)", "67%") in summary_lines(res)
