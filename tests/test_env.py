"""The gymnasium env: check_env, determinism, reward terms, contract, batching, baselines."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import sim.env  # registers hydo/Bin-v0; the flip_share test spies on it
from sim.baselines import heuristic_action
from sim.contract import FEATURE_DIM, SUCCESS_THRESHOLD_M, validate_observation
from sim.env import BinEnv
from sim.primitive import feasibility_mask


def feasible_heuristic(obs: dict) -> tuple[int, np.ndarray]:
    """The heuristic's push among the points whose push can run (as the learned policies choose)."""
    mask = feasibility_mask(obs["points"][None], obs["normals"][None])
    return heuristic_action(obs, np.random.default_rng(0), mask)


@pytest.mark.parametrize("goals, contacts", [("planar", "hydo"), ("6d", "hydo"), ("6d", "hacman")])
def test_check_env(goals, contacts):
    env = gymnasium.make("hydo/Bin-v0", objects="cube", goals=goals, contacts=contacts).unwrapped
    check_env(env, skip_render_check=True)
    assert env.scene.contacts == contacts


def test_make_kwargs_and_spaces():
    env = gymnasium.make("hydo/Bin-v0", objects="train", goals="6d", n_obj=32, n_bg=16)
    obs, info = env.reset(seed=3)
    assert obs["points"].shape == (48, 3) and obs["features"].shape == (48, FEATURE_DIM)
    assert obs["normals"].shape == (32, 3)
    validate_observation(obs, 32, 16)
    assert env.observation_space.contains(obs)
    # object points first: is_object flag is 1 exactly for the first n_obj points
    assert np.all(obs["features"][:32, 0] == 1) and np.all(obs["features"][32:, 0] == 0)
    assert np.all(obs["features"][32:, 1:] == 0)


def test_bad_arguments():
    with pytest.raises(ValueError, match="goals"):
        BinEnv(objects="cube", goals="7d")
    with pytest.raises(ValueError, match="clutter"):
        BinEnv(objects="cube", clutter=3)
    with pytest.raises(ValueError, match="contacts"):
        BinEnv(objects="cube", contacts="robosuite")


def _rollout(seed, n=4):
    env = BinEnv(objects="train", goals="6d")
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    trace = [obs["points"].copy()]
    for _ in range(n):
        action = (int(rng.integers(env.n_obj)), rng.uniform(-1, 1, 3))
        obs, r, term, trunc, info = env.step(action)
        trace.append(obs["points"].copy())
        trace.append(np.array([r]))
        if term or trunc:
            break
    return trace


def test_seeding_is_exactly_reproducible():
    a, b = _rollout(7), _rollout(7)
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    c = _rollout(8)
    assert not np.array_equal(a[0], c[0])


def test_reward_is_minus_the_mean_goal_flow_and_success_threshold():
    """The reward recomputed by hand, without the contract's helpers: −mean ‖T_goal·p − T_obj·p‖ over
    the object's own-frame surface samples p, with both poses built from ``info`` by scipy."""
    from scipy.spatial.transform import Rotation

    def matrix(pose):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(pose[3:], scalar_first=True).as_matrix()
        T[:3, 3] = pose[:3]
        return T

    env = BinEnv(objects="train", goals="planar")
    obs, _ = env.reset(seed=0)
    _, r, term, _, info = env.step(feasible_heuristic(obs))
    assert not info["rejected"]  # the push ran: the object moved
    p = env.scene.asset.surface_points
    p = np.concatenate([p, np.ones((len(p), 1))], axis=1)
    dist = np.linalg.norm((p @ (matrix(info["goal_pose"]) - matrix(info["object_pose"])).T)[:, :3], axis=1)
    assert r == pytest.approx(-dist.mean(), rel=1e-5) and r < 0
    assert info["reward_flow"] == r and info["distance"] == pytest.approx(dist.mean())
    assert info["success"] == (dist.mean() < SUCCESS_THRESHOLD_M) == term


def test_info_poses_reproduce_the_observed_goal_flow():
    """Hindsight relabelling rebuilds goal flows from ``info``'s poses: they must be the poses the
    next observation was built from."""
    from sim.contract import goal_flow, pose_matrix

    env = BinEnv(objects="train", goals="6d", n_obj=64, n_bg=32)
    obs, _ = env.reset(seed=4)
    obs, *_, info = env.step(feasible_heuristic(obs))
    assert not info["rejected"]  # a push that ran, so the pose after it is a new one
    T_obj = pose_matrix(info["object_pose"][:3], info["object_pose"][3:])
    T_goal = pose_matrix(info["goal_pose"][:3], info["goal_pose"][3:])
    want = goal_flow(obs["points"][:64], T_obj, T_goal)
    np.testing.assert_allclose(obs["features"][:64, 1:], want, atol=1e-5)
    # the tilt still left after the step (eval's failed flips that never turned over), from the same poses
    assert info["goal_tilt_deg"] == pytest.approx(_least_tilt(T_obj, T_goal, env.scene.asset), abs=1e-6)


def _least_tilt(T_now, T_goal, asset) -> float:
    """The tilt between the up directions at ``T_now`` and the nearest of the goal's symmetric poses,
    written out plainly: one symmetry at a time, in the world frame."""
    from sim.symmetry import symmetries

    tilts = []
    for S in symmetries(asset):
        up_goal = (T_goal @ S)[:3, :3].T @ [0, 0, 1]  # world up in the object frame at the goal
        up_now = T_now[:3, :3].T @ [0, 0, 1]
        tilts.append(np.degrees(np.arccos(np.clip(up_goal @ up_now, -1, 1))))
    return min(tilts)


def test_reset_reports_how_far_the_goal_tilts_the_object():
    """``goal_tilt_deg``: 0 for planar goals; for 6D goals the least angle between the up directions
    of the start and the goal's symmetric poses, so flips read ≥ 30° and yaws 0."""
    from sim.contract import pose_matrix

    planar = BinEnv(objects="train", goals="planar", n_obj=32, n_bg=16)
    # settling tilts a start by hundredths of a degree; a near-symmetry (a mug's handle, lying on its
    # side) may stand in for the goal turned ~10° about the horizontal axis: never a flip
    planar_tilts = [planar.reset(seed=s)[1]["goal_tilt_deg"] for s in range(10)]
    assert max(planar_tilts) < 15 and np.median(planar_tilts) < 0.1
    env = BinEnv(objects="train", goals="6d", n_obj=32, n_bg=16)
    tilts = []
    for s in range(40):
        _, info = env.reset(seed=s)
        want = _least_tilt(pose_matrix(*env.scene.object_pose()), env.T_goal_eff, env.scene.asset)
        assert info["goal_tilt_deg"] == pytest.approx(want, abs=1e-6)
        tilts.append(info["goal_tilt_deg"])
    assert min(tilts) < 5 and max(tilts) > 60  # 6D goals include yaws and flips


def test_flip_share_mixes_training_goals_and_none_keeps_the_episodes(monkeypatch):
    """``flip_share`` (training's goal mix): 1 draws only flips, 0 only moves; None draws as before,
    so evaluation episodes (which never set it) stay the same episodes."""
    from sim.goals import FLIP_TILT_DEG, sample_start_and_goal

    for share, is_flip in ((1.0, True), (0.0, False)):
        env = BinEnv(objects="box_00", goals="6d", n_obj=32, n_bg=16, flip_share=share)
        tilts = [env.reset(seed=s)[1]["goal_tilt_deg"] for s in range(12)]
        assert all((t >= FLIP_TILT_DEG) == is_flip for t in tilts), (share, tilts)
    drawn = BinEnv(objects="box_00", goals="6d", n_obj=32, n_bg=16)
    mixed = BinEnv(objects="box_00", goals="6d", n_obj=32, n_bg=16, flip_share=0.5)
    mixed.flip_share = None  # what the trainer does for its evaluations
    for s in range(3):
        drawn.reset(seed=s)
        mixed.reset(seed=s)
        np.testing.assert_array_equal(drawn.T_goal, mixed.T_goal)
    # a cube looks the same on every face (sim.goals.can_flip): the sampler is not asked for a flip
    # there is none of (GOAL_TRIES draws spent on every reset), while a box is
    asked = []

    def spy(*args, flip=None, **kwargs):
        asked.append(flip)
        return sample_start_and_goal(*args, flip=flip, **kwargs)

    monkeypatch.setattr(sim.env, "sample_start_and_goal", spy)
    for objects in ("cube", "box_00"):
        env = BinEnv(objects=objects, goals="6d", n_obj=32, n_bg=16, flip_share=1.0)
        tilts = [env.reset(seed=s)[1]["goal_tilt_deg"] for s in range(3)]
        assert all((t >= FLIP_TILT_DEG) == (objects == "box_00") for t in tilts), (objects, tilts)
    assert asked == [None] * 3 + [True] * 3
    with pytest.raises(ValueError, match="flip_share"):
        BinEnv(objects="box_00", goals="planar", flip_share=0.5)


def test_can_flip_is_whether_another_face_can_be_up_whatever_the_symmetry():
    """``sim.goals.can_flip``: a box can show another face; a cube (every face alike), a capsule (it
    rests only on its side, any roll alike) and a torus (upside down is itself) cannot, unless goals
    are exact poses; and where it says no, flip requests find none, and where yes, they always do."""
    from sim.contract import pose_matrix
    from sim.goals import FLIP_TILT_DEG, can_flip, sample_start_and_goal, tilt_deg
    from sim.objects import load_objects
    from sim.symmetry import symmetries

    by_name = {a.name: a for a in load_objects("train") + load_objects("unseen")}
    assert can_flip(by_name["box_00"]) and can_flip(by_name["wedge_00"])
    for name in ("cube", "capsule_00", "torus_00"):
        assert not can_flip(by_name[name]), name
    assert can_flip(by_name["cube"], symmetric=False)  # exact poses: another face is another pose
    for name in ("box_00", "torus_00", "u_prism_00"):
        asset, rng = by_name[name], np.random.default_rng(0)
        for _ in range(4):
            (p, q), (gp, gq) = sample_start_and_goal(asset, "6d", rng, flip=True)
            tilt = tilt_deg(pose_matrix(p, q), pose_matrix(gp, gq), symmetries(asset))
            assert (tilt >= FLIP_TILT_DEG) == can_flip(asset), (name, tilt)


def test_goal_reached_when_object_placed_at_goal():
    env = BinEnv(objects="cube", goals="6d")
    env.reset(seed=1)
    env.scene.set_object_pose(*env.goal_pose)
    reward, success, dist = env._evaluate()
    assert success and dist < 1e-6


def test_rejected_primitive_leaves_scene_unchanged():
    env = BinEnv(objects="cube", goals="planar")
    env.reset(seed=2)
    # a cube next to the +x wall, pushed from its +x face: the pre-contact waypoint lies behind the wall
    env.scene.set_object_pose(np.array([0.19, 0.0, 0.03]), np.array([1.0, 0, 0, 0]))
    obs = env._observe()
    before = env.scene.get_state().copy()
    n_obj = env.n_obj
    i = int(np.argmax(obs["normals"][:, 0] * (obs["points"][:n_obj, 2] > 0.01)))
    _, _, _, _, info = env.step((i, np.array([1.0, 0.0, 0.0])))
    assert info["rejected"] and "workspace" in info["reject_reason"]
    np.testing.assert_array_equal(env.scene.get_state(), before)


def test_sim_state_snapshot_replays_a_push_exactly():
    """A planner's try-and-go-back (bench/lookahead.py): the same push from a restored snapshot ends
    in the same pose, bit for bit, and the episode's step count is restored with it."""
    env = BinEnv(objects="train", goals="planar")
    obs, _ = env.reset(seed=3)
    index, motion = heuristic_action(obs, np.random.default_rng(0))
    snapshot = env.get_sim_state()
    start = np.concatenate(env.scene.object_pose())
    _, _, _, _, first = env.step((index, motion))
    pose = np.concatenate(env.scene.object_pose())
    assert first["physics_steps"] > 0 and not first["rejected"]
    assert np.linalg.norm(pose[:3] - start[:3]) > 0.005  # the push moved the object
    env.set_sim_state(snapshot)
    assert env._steps == 0
    np.testing.assert_array_equal(env.scene.get_state(), snapshot["physics"])
    _, _, _, _, again = env.step((index, motion))
    np.testing.assert_array_equal(np.concatenate(env.scene.object_pose()), pose)
    assert again["distance"] == first["distance"]
    other = next(a.name for a in env.assets if a.name != first["object"])
    env.reset(seed=4, options={"object": other})
    with pytest.raises(ValueError, match="another episode's scene"):
        env.set_sim_state(snapshot)


def test_truncation_after_ten_primitives():
    env = BinEnv(objects="cube", goals="planar")
    env.reset(seed=4)
    for _k in range(10):
        _, _, term, trunc, info = env.step((0, np.zeros(3)))
        assert not term, "a null push cannot reach a goal that starts > 5 cm away"
    assert trunc and info["failure"] == "timeout"
    # the distance left, split into placing and turning on the step that ends it (flow_split's bounds)
    pos, rot = info["final_position_m"], info["final_rotation_m"]
    assert pos <= info["distance"] + 1e-6 <= pos + rot + 2e-6


def test_flow_split_separates_placing_from_turning():
    """A pure translation is all placing, a turn about the centroid all turning; the two bound the
    mean goal flow from both sides at any pose (the turn's flow written out by hand)."""
    from scipy.spatial.transform import Rotation

    from sim.contract import flow_split, mean_flow_distance, pose_matrix

    rng = np.random.default_rng(0)
    p_obj = rng.normal(scale=0.03, size=(400, 3))  # object-frame points, metres
    T_obj = pose_matrix(np.array([0.05, -0.02, 0.03]), np.array([1.0, 0.0, 0.0, 0.0]))
    points = p_obj + T_obj[:3, 3]
    moved = T_obj.copy()
    moved[:3, 3] += [0.04, 0.0, -0.03]  # 5 cm away, same orientation
    assert flow_split(points, T_obj, moved) == pytest.approx((0.05, 0.0), abs=1e-7)  # float32 flow
    centroid = points.mean(axis=0)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    turn[:3, 3] = centroid - turn[:3, :3] @ centroid  # about the centroid
    pos, rot = flow_split(points, T_obj, turn @ T_obj)
    want = np.linalg.norm(points @ turn[:3, :3].T + turn[:3, 3] - points, axis=1).mean()
    assert pos == pytest.approx(0.0, abs=1e-7) and rot == pytest.approx(want, rel=1e-5) and rot > 0.01
    for _ in range(5):
        T_goal = np.eye(4)
        T_goal[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T_goal[:3, 3] = rng.uniform(-0.1, 0.1, 3)
        pos, rot = flow_split(points, T_obj, T_goal)
        d = mean_flow_distance(points, T_obj, T_goal)
        assert pos <= d + 1e-6 <= pos + rot + 2e-6


def test_vector_env_steps_a_batch_in_one_process():
    envs = gymnasium.vector.SyncVectorEnv([lambda: BinEnv(objects="train", goals="planar") for _ in range(3)])
    obs, _ = envs.reset(seed=0)
    assert obs["points"].shape[0] == 3
    actions = (np.zeros(3, dtype=np.int64), np.zeros((3, 3), dtype=np.float32))
    obs, r, term, trunc, _ = envs.step(actions)
    assert r.shape == (3,)
    envs.close()


def test_clutter_enters_background():
    env = BinEnv(objects="cube", goals="planar", clutter=2)
    obs, _ = env.reset(seed=0)
    assert len(env.scene.clutter) == 2
    bg = obs["points"][env.n_obj :]
    # some background points are above the floor and away from the walls: the clutter objects
    inner = (np.abs(bg[:, 0]) < 0.2) & (np.abs(bg[:, 1]) < 0.25) & (bg[:, 2] > 0.01)
    assert inner.sum() > 0


def test_a_push_that_leaves_the_object_where_it_was_is_idle():
    """``info["idle"]``: the primitive ran and the object stayed (under 3 mm and 2°). A tap on the
    cube's top lifted straight off is idle; the heuristic's push into its side is not."""
    env = BinEnv(objects="cube", goals="planar", n_obj=64, n_bg=32)
    obs, _ = env.reset(seed=2)
    top = int(np.argmax(obs["points"][:64, 2]))
    states = env.get_sim_state()
    before = np.concatenate(env.scene.object_pose())
    *_, info = env.step((top, np.array([0.0, 0.0, 1.0])))
    assert info["idle"] and not info["rejected"], info["reject_reason"]
    assert np.linalg.norm(info["object_pose"][:3] - before[:3]) < 0.003  # object_pose: after the push
    env.set_sim_state(states)
    *_, info = env.step(feasible_heuristic(obs))
    assert not info["idle"] and not info["rejected"]
    assert np.linalg.norm(info["object_pose"][:3] - before[:3]) > 0.01
