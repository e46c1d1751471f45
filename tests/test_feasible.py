"""Feasible contact points: the location policy's pre-check of a push against the workspace gate and
the simulator's start-pose collision test, and its use by the torch agent and the ONNX policy."""

import numpy as np
import pytest
import torch

from models.algos import AgentConfig, HybridAgent
from sim.env import BinEnv
from sim.objects import load_objects
from sim.primitive import (
    HAND_BOXES,
    START_TOLERANCE_M,
    PrimitiveRejected,
    check_plan,
    feasibility_mask,
    feasible_points,
    plans_inside,
    primitive_waypoints,
    start_clear,
    within_walls,
)
from sim.scene import START_PENETRATION_M, BinScene
from tests.models.learner_util import SMALL


def test_hand_boxes_match_the_simulated_hand():
    scene = BinScene(load_objects("cube")[0])
    m = scene.model
    for name, (centre, half) in zip(("hand_fingers", "hand_palm"), HAND_BOXES, strict=True):
        g = m.geom(name)
        np.testing.assert_allclose(g.pos, centre, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(g.size, half, atol=1e-9, err_msg=name)
    assert START_TOLERANCE_M == START_PENETRATION_M


def test_batched_waypoints_and_gate_agree_with_the_single_plan_versions():
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.25, 0.25, (3, 40, 3))
    n, m = rng.normal(size=(3, 40, 3)), rng.uniform(-1.2, 1.2, (3, 40, 3))
    w, ok = primitive_waypoints(p, n, m), plans_inside(primitive_waypoints(p, n, m))
    for b in range(3):
        for i in range(40):
            wi = primitive_waypoints(p[b, i], n[b, i], m[b, i])
            np.testing.assert_allclose(w[b, i], wi)
            try:
                check_plan(wi)
                accepted = True
            except PrimitiveRejected:
                accepted = False
            assert ok[b, i] == accepted
    assert 0.1 < ok.mean() < 0.9  # both outcomes are exercised


def test_prediction_matches_the_simulator_on_random_pushes():
    """Random pushes on the training objects: every push whose start is predicted in collision (or
    outside the workspace) is refused by the simulator, and most refusals are predicted (the rest: hand clear of the sparse cloud but not of
    the mesh)."""
    env = BinEnv("train", "planar")
    rng = np.random.default_rng(1)
    counts = {"predicted_refusal": 0, "refused": 0, "caught": 0, "false_refusal": 0}
    for ep in range(40):
        obs, _ = env.reset(seed=ep)
        for _ in range(4):
            i, motion = int(rng.integers(env.n_obj)), rng.uniform(-1, 1, 3).astype(np.float32)
            motions = np.broadcast_to(motion, (1, env.n_obj, 3))
            waypoints = primitive_waypoints(obs["points"][None, : env.n_obj], obs["normals"][None], motions)
            pred = plans_inside(waypoints) & start_clear(waypoints[..., 0, :], obs["points"][None])
            obs, _, term, trunc, info = env.step((i, motion))
            counts["predicted_refusal"] += not pred[0, i]
            counts["refused"] += info["rejected"]
            counts["caught"] += info["rejected"] and not pred[0, i]
            counts["false_refusal"] += (not info["rejected"]) and not pred[0, i]
            if term or trunc:
                break
    assert counts["refused"] >= 20, counts  # random pushes are refused often: the test has material
    assert counts["false_refusal"] == 0, counts
    assert counts["caught"] >= 0.8 * counts["refused"], counts


def test_mask_allows_every_point_in_rows_without_a_feasible_one():
    """Row 0: one point whose push heads into the wall is masked; row 1: every push is refused, so the
    mask allows all points (the gate then refuses the plan with its reason)."""
    point = np.array([[[0.0, -0.1, 0.03], [0.0, 0.0, 0.03]], [[0.0, -0.1, 0.03], [0.0, -0.1, 0.03]]])
    normal = np.broadcast_to(np.array([0.0, 1.0, 0.0]), point.shape)
    cloud = np.concatenate([point, np.zeros((2, 1, 3))], axis=1)  # object points first, one floor point
    toward_wall, away = [0.0, -1.0, 0.0], [0.0, 1.0, 0.0]
    motions = np.array([[toward_wall, away], [toward_wall, toward_wall]])
    mask = feasibility_mask(cloud, normal)(motions)
    assert mask.shape == (2, 2) and mask.dtype == bool
    np.testing.assert_array_equal(mask, [[False, True], [True, True]])


@pytest.mark.parametrize("algo", ["hacman", "hydo-cm"])
def test_agent_only_chooses_feasible_points(algo):
    env = BinEnv("train", "planar", n_obj=32, n_bg=32)
    agent = HybridAgent(AgentConfig(algo=algo, **{**SMALL, "n_obj": 32, "n_bg": 32}))
    g = torch.Generator().manual_seed(0)
    chosen_infeasible = argmax_infeasible = 0
    for ep in range(12):
        obs, _ = env.reset(seed=ep)
        pts, feats = torch.from_numpy(obs["points"][None]), torch.from_numpy(obs["features"][None])
        normals = torch.from_numpy(obs["normals"][None])
        mask = feasibility_mask(obs["points"][None], obs["normals"][None])
        for mode in ("explore", "eval"):
            index, _, info = agent.act(pts, feats, mode=mode, generator=g, normals=normals, feasible=mask)
            feasible = feasible_points(
                obs["points"][None, :32], obs["normals"][None], info["motions"].numpy(), obs["points"][None]
            )
            if feasible.any():
                chosen_infeasible += not feasible[0, int(index[0])]
                argmax_infeasible += not feasible[0, int(info["q"][0].argmax())]
    assert chosen_infeasible == 0
    assert argmax_infeasible > 0  # the plain argmax of Q would have chosen infeasible points: the mask acted


def test_palm_must_stay_off_the_walls_through_the_push():
    """The 20 cm palm (4.6 cm above the fingertip) over the rim's inside: refused below the rim, fine
    above it or away from the wall; and feasible_points applies it to every push waypoint."""
    assert not within_walls(np.array([0.0, -0.2, 0.03]))  # palm reaches y = -0.302 < -0.27 below the rim
    assert within_walls(np.array([0.0, -0.2, 0.2]))  # palm above the rim
    assert within_walls(np.array([0.0, 0.0, 0.03]))
    point, normal = np.array([[[0.0, -0.1, 0.03]]]), np.array([[[0.0, 1.0, 0.0]]])
    toward_wall, away = np.array([[[0.0, -1.0, 0.0]]]), np.array([[[0.0, 1.0, 0.0]]])
    cloud = np.zeros((1, 1, 3))  # one point on the floor, far from the hand boxes
    assert within_walls(primitive_waypoints(point, normal, away)[..., 0, :])  # the start alone is fine
    assert feasible_points(point, normal, away, cloud)[0, 0]
    assert not feasible_points(point, normal, toward_wall, cloud)[0, 0]  # push ends at y = -0.19


def test_heuristic_pushes_only_where_the_mask_allows():
    """The scripted heuristic gets the learned policies' feasibility mask: on observations where it
    would otherwise pick points whose push the gate or the start-pose test refuses, it picks only
    feasible points (when any exist), and its motion is unchanged."""
    from sim.baselines import heuristic_action

    env = BinEnv("train", "planar")
    masked_ok, unmasked_bad = [], 0
    for seed in range(40):
        obs, _ = env.reset(seed=seed)
        pts, nrm = obs["points"][None], obs["normals"][None]
        mask = feasibility_mask(pts, nrm)
        i0, m0 = heuristic_action(obs, np.random.default_rng(seed))
        i1, m1 = heuristic_action(obs, np.random.default_rng(seed), mask)
        np.testing.assert_array_equal(m0, m1)
        allowed = mask(np.broadcast_to(m1, (1, len(nrm[0]), 3)))[0]
        if not allowed.all():  # rows with no feasible point allow every point
            masked_ok.append(bool(allowed[i1]))
            unmasked_bad += int(not allowed[i0])
    assert masked_ok and all(masked_ok)
    assert unmasked_bad > 0  # the unmasked heuristic does pick refused points on these episodes
