"""Goals up to the object's symmetry: the symmetries found from the mesh, and the env's flow, reward
and success going to the nearest pose that looks exactly like the goal."""

from __future__ import annotations

import numpy as np
import pytest

from sim.contract import SUCCESS_THRESHOLD_M, pose_matrix, symmetric_goal, transform_points
from sim.objects import load_objects
from sim.symmetry import find_symmetries, symmetries


def angle_axis(T: np.ndarray) -> tuple[float, np.ndarray]:
    R = T[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    n = np.linalg.norm(axis)
    return float(angle), axis / n if n > 1e-9 else axis


def has_turn(S: np.ndarray, axis, degrees: float, tol_deg: float = 2.0) -> bool:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    for T in S:
        a, ax = angle_axis(T)
        if abs(a - degrees) < tol_deg and abs(abs(ax @ axis) - 1) < 0.01:
            return True
        if abs(degrees - 180) < tol_deg and abs(a - 180) < tol_deg:
            # a half turn's axis is not defined by the antisymmetric part: check R maps axis to itself
            R = T[:3, :3]
            if np.allclose(R @ axis, axis, atol=0.02):
                return True
    return False


def test_found_symmetries_of_a_cube_a_box_a_cylinder_and_a_mug():
    (cube,) = load_objects("cube")
    S = symmetries(cube)
    assert np.allclose(S[0], np.eye(4))
    assert 24 <= len(S) <= 26  # the rotation group of a cube (and at most a near-duplicate)
    assert has_turn(S, [0, 0, 1], 90) and has_turn(S, [1, 1, 1], 120) and not has_turn(S, [0, 0, 1], 45)

    (box,) = load_objects("box_00")  # three different side lengths: the identity and three half turns
    S = symmetries(box)
    assert has_turn(S, [0, 0, 1], 180) and not has_turn(S, [0, 0, 1], 90)
    assert all(round(angle_axis(T)[0]) in (0, 180) for T in S)

    (cyl,) = load_objects("cylinder_00")  # about its axis in 10° steps, and end over end
    S = symmetries(cyl)
    assert has_turn(S, [0, 0, 1], 40) and has_turn(S, [0, 0, 1], 130) and len(S) >= 36

    (mug,) = load_objects("mug_00")  # the handle: no turn about its axis of 30° or more
    S = find_symmetries(mug.surface_points)
    assert all(angle_axis(T)[0] < 25 for T in S)


def test_the_nearest_symmetric_goal_and_its_distance():
    """A cylinder whose goal is the start rolled 130° about its own axis is already at its goal; with
    no symmetries (a mug turned the same way) the flow is the full turn."""
    (cyl,) = load_objects("cylinder_00")
    T_obj = pose_matrix(np.array([0.1, 0.0, 0.03]), np.array([1.0, 0, 0, 0]))
    c = (cyl.surface_points.min(0) + cyl.surface_points.max(0)) / 2
    spin = np.eye(4)
    a = np.deg2rad(130)
    spin[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    spin[:3, 3] = c - spin[:3, :3] @ c
    T_goal = T_obj @ spin
    surf = transform_points(T_obj, cyl.surface_points)

    def distance(T):
        return np.linalg.norm(transform_points(T @ np.linalg.inv(T_obj), surf) - surf, axis=1).mean()

    assert distance(T_goal) > 0.02  # the exact pose: a visible-to-nobody turn
    T_eff = symmetric_goal(T_obj, T_goal, cyl.surface_points, symmetries(cyl))
    assert distance(T_eff) < 0.002 < SUCCESS_THRESHOLD_M
    assert np.array_equal(symmetric_goal(T_obj, T_goal, cyl.surface_points, np.eye(4)[None]), T_goal)


@pytest.mark.parametrize("goals", ["planar", "6d"])
def test_env_distance_is_up_to_symmetry_and_never_above_the_exact_one(goals):
    """Same episodes with ``goal_symmetry="object"`` (the default) and ``"none"``: the same objects,
    starts and goals; the distance to the goal up to symmetry is never larger (smaller for some 6D
    episodes of symmetric objects); the observation's goal flow is the reward's."""
    from sim.env import BinEnv

    sym, exact = BinEnv(goals=goals), BinEnv(goals=goals, goal_symmetry="none")
    smaller = 0
    for seed in range(12):
        obs_s, info_s = sym.reset(seed=seed)
        _, info_e = exact.reset(seed=seed)
        assert info_s["object"] == info_e["object"]
        assert info_s["distance"] <= info_e["distance"] + 1e-9
        smaller += info_s["distance"] < info_e["distance"] - 1e-3
        flow = obs_s["features"][: sym.n_obj, 1:]
        # the observation's flow is T_goal_eff·T_obj⁻¹·p − p for the observed points
        pts = obs_s["points"][: sym.n_obj]
        want = transform_points(sym.T_goal_eff @ np.linalg.inv(sym.scene.object_T()), pts) - pts
        np.testing.assert_allclose(flow, want, atol=1e-5)
    # a planar goal keeps the start's stable pose and yaw, so at reset the nearest symmetric goal is
    # the goal itself; a 6D goal's stable pose and yaw are new: some are nearer by a symmetry
    assert smaller > 0 if goals == "6d" else smaller == 0
    with pytest.raises(ValueError, match="goal_symmetry"):
        BinEnv(goal_symmetry="mirror")
    sym.close()
    exact.close()


def test_6d_episodes_start_away_from_the_goal_up_to_symmetry():
    """The goal sampler measures the start's distance as the reward does: a 6D goal that is the start
    turned by one of the object's symmetries is re-drawn, never an episode solved before it starts."""
    from sim.env import BinEnv
    from sim.goals import GOAL_TRIES, MIN_GOAL_DISTANCE_M

    assets = tuple(a for name in ("cube", "cylinder_00", "box_00") for a in load_objects(name))
    env = BinEnv(objects=assets, goals="6d")
    distances = [env.reset(seed=s)[1]["distance"] for s in range(40)]
    assert GOAL_TRIES > 1 and min(distances) > MIN_GOAL_DISTANCE_M
    env.close()


def test_symmetric_goals_pick_as_the_plain_formula_bit_for_bit():
    """SymmetricGoals (the env's per-goal cache, coordinate-major, without np.linalg.norm) picks the
    same goal as the plain formula: rank T_goal·S on a strided subset by mean flow, then the best
    few and the goal itself on all samples."""
    from sim.contract import SYMMETRY_FINALISTS, SYMMETRY_PROBE_POINTS, SymmetricGoals

    def plain(T_obj, T_goal, pts, S):
        goals = T_goal[None] @ S

        def mean_flow(G, p):
            return np.linalg.norm(
                G[:, :3, :3] @ p.T + G[:, :3, 3:] - transform_points(T_obj, p).T, axis=1
            ).mean(1)

        probe = pts[:: max(1, len(pts) // SYMMETRY_PROBE_POINTS)]
        finalists = np.unique(np.r_[0, np.argsort(mean_flow(goals, probe))[:SYMMETRY_FINALISTS]])
        return goals[finalists[int(np.argmin(mean_flow(goals[finalists], pts)))]]

    rng = np.random.default_rng(0)
    for name in ("cylinder_00", "box_00", "cube"):
        (asset,) = load_objects(name)
        S = symmetries(asset)
        T_goal = pose_matrix(rng.uniform(-0.1, 0.1, 3), rng.normal(size=4))
        goals = SymmetricGoals(T_goal, asset.surface_points, S)
        for k in range(30):
            T_obj = pose_matrix(rng.uniform(-0.1, 0.1, 3), rng.normal(size=4))
            if k % 3 == 0:  # near one of the symmetric goals: close finalists
                T_obj = (
                    T_goal
                    @ S[rng.integers(len(S))]
                    @ pose_matrix(rng.normal(0, 0.003, 3), [1, *rng.normal(0, 0.02, 3)])
                )
            want = plain(T_obj, T_goal, asset.surface_points, S)
            assert np.array_equal(goals.nearest(T_obj), want)
            assert np.array_equal(goals.nearest(T_obj, transform_points(T_obj, asset.surface_points)), want)
            assert np.array_equal(symmetric_goal(T_obj, T_goal, asset.surface_points, S), want)
