"""``hydo/Bin-v0``: HACMan's object pose alignment task as a gymnasium env.

Observation
    ``Dict(points (N, 3), features (N, 4), normals (N_obj, 3))`` float32, the layout of
    ``sim.contract`` (object points first, then background; features ``[is_object, goal_flow]``).
Action
    ``Tuple(Discrete(N_obj), Box(-1, 1, (3,)))``: the index of the contact point among the object
    points of the current observation, and the motion parameter of the push primitive
    (``sim.primitive``: three pushes of ``0.03 · motion`` metres).
Reward
    ``−mean_i ‖goal_flow_i‖`` (metres) over the object's full surface samples at the new pose;
    ``info["reward_flow"]`` holds the same term (the reward is the sum of the ``reward_*`` terms).
    The flow goes to the nearest pose that looks exactly like the goal pose (``goal_symmetry="object"``,
    ``sim.contract.symmetric_goal``: a cylinder's roll, a box turned 180° are not asked for);
    ``goal_symmetry="none"``: to the goal pose itself (the task before symmetric goals).
Episode end
    terminated on success (mean flow < 3 cm) or when the object leaves the bin; truncated after
    ``MAX_PRIMITIVES`` (10) primitives. A refused primitive (a waypoint outside the workspace, or a
    start pose in collision) leaves the scene unchanged, counts as a step and is reported in
    ``info["rejected"]`` / ``info["reject_reason"]``. ``info["object_pose"]`` and ``info["goal_pose"]``
    hold the object pose after the primitive and the goal pose (position + quaternion wxyz, (7,)).
    On the step that ends an episode, ``info["final_position_m"]`` and ``info["final_rotation_m"]``
    split the distance left into placing and turning (``sim.contract.flow_split``).
Arguments (``gymnasium.make("hydo/Bin-v0", ...)``)
    ``objects`` (split name, object name or mesh folder), ``goals`` (``planar`` | ``6d``), ``obs``
    (``mesh`` | ``render``), ``clutter`` (0, 1, 2 or 5 extra objects in the background cloud),
    ``n_obj``, ``n_bg`` (point counts), ``max_steps``, ``goal_symmetry`` (``object`` | ``none``),
    ``flip_share`` (6D, training: the share of episodes whose goal is a flip; None: as drawn, ~half);
    ``contacts`` (``hydo`` | ``hacman``: the scene's contact model, set by ``sim.scene``);
    ``task`` (``sim.tasks``: ``push-line`` |
    ``push-align``, the behaviour-diversity variants; they fix the object, goal and obstacles) and
    ``task_start`` (``fixed``: the task's fixed start pose, for evaluation; ``random``: its training
    start region). With a task, ``info["behaviour"]`` holds the episode's behaviour id (or None) on
    the step that ends it.
Starting state
    A random stable pose of a random object, with random yaw and bin position; ``planar`` goals
    translate it (same orientation), ``6d`` goals pick another random stable pose, yaw and position.
    ``reset``'s info holds ``object``, ``distance`` and ``goal_tilt_deg``: how far the goal tilts the
    object's up direction (up to its symmetry; 0 for planar goals, ~90 or ~180 for a flip).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sim.contract import (
    CONTACT_MODELS,
    DEFAULT_N_BG,
    DEFAULT_N_OBJ,
    FEATURE_DIM,
    GOAL_MODES,
    MAX_PRIMITIVES,
    OBS_SOURCES,
    SymmetricGoals,
    build_observation,
    flow_split,
    pose_matrix,
    reward_and_success,
)
from sim.goals import (
    can_flip,
    footprint_radius,
    quat_angle,
    sample_object,
    sample_placement,
    sample_start_and_goal,
    stable_poses,
    tilt_deg,
)
from sim.objects import ObjectAsset, load_objects
from sim.observe import MeshObserver
from sim.primitive import SIM_WORKSPACE, PrimitiveRejected, check_plan, primitive_waypoints
from sim.scene import BinScene
from sim.symmetry import symmetries
from sim.tasks import TaskStep, get_task

CLUTTER_CHOICES = (0, 1, 2, 5)
GOAL_SYMMETRIES = ("object", "none")
#: A primitive that ran but left the object within this of where it was is *idle* (``info["idle"]``):
#: the fingers missed it or pulled away. 3 mm and 2° are well under one push segment (3 cm) and over
#: what settling moves a resting object.
IDLE_MOVE_M = 0.003
IDLE_TURN_RAD = np.deg2rad(2.0)


class BinEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(
        self,
        objects: str | tuple[ObjectAsset, ...] = "train",
        goals: str = "planar",
        obs: str = "mesh",
        clutter: int = 0,
        n_obj: int = DEFAULT_N_OBJ,
        n_bg: int = DEFAULT_N_BG,
        max_steps: int = MAX_PRIMITIVES,
        render_mode: str | None = None,
        task: str | None = None,
        task_start: str = "fixed",
        goal_symmetry: str = "object",
        flip_share: float | None = None,
        contacts: str = "hydo",
    ):
        if contacts not in CONTACT_MODELS:
            raise ValueError(f"`contacts` must be one of {list(CONTACT_MODELS)}. Got {contacts!r}.")
        self.contacts = contacts
        if goal_symmetry not in GOAL_SYMMETRIES:
            raise ValueError(
                f"`goal_symmetry` must be one of {list(GOAL_SYMMETRIES)}. Got {goal_symmetry!r}."
            )
        self.goal_symmetry = goal_symmetry
        self._symmetries: dict[str, np.ndarray] = {}
        self._goal_key: tuple | None = None
        self._goal_poses: tuple[tuple, SymmetricGoals] | None = None  # the goal's symmetric poses
        if goals not in GOAL_MODES:
            raise ValueError(f"`goals` must be one of {list(GOAL_MODES)}. Got {goals!r}.")
        if clutter not in CLUTTER_CHOICES:
            raise ValueError(f"`clutter` must be one of {list(CLUTTER_CHOICES)}. Got {clutter!r}.")
        if obs not in OBS_SOURCES:
            raise ValueError(f"`obs` must be one of {list(OBS_SOURCES)}. Got {obs!r}.")
        self.task = None if task is None else get_task(task)  # behaviour-diversity variant (sim.tasks)
        if self.task is not None:
            if task_start not in ("fixed", "random"):
                raise ValueError(f"`task_start` must be one of ['fixed', 'random']. Got {task_start!r}.")
            if clutter:
                raise ValueError(
                    f"`clutter` must be 0 with a task (its obstacles are the scene). Got {clutter!r}."
                )
            objects = self.task.object
        self.task_start = task_start
        self._trajectory: list[TaskStep] = []
        self.assets = load_objects(objects) if isinstance(objects, str) else tuple(objects)
        if not self.assets:
            raise ValueError("no objects to train or evaluate on")
        self.goal_mode, self.n_clutter = goals, clutter
        if flip_share is not None and (goals != "6d" or not 0.0 <= flip_share <= 1.0):
            raise ValueError(f"`flip_share` is a fraction in [0, 1] for 6D goals. Got {flip_share!r}.")
        self.flip_share = flip_share  # public: a trainer evaluates with None (goals as drawn)
        self._can_flip: dict[str, bool] = {}  # sim.goals.can_flip per object, asked on its first flip request
        self.n_obj, self.n_bg, self.max_steps = n_obj, n_bg, max_steps
        self.render_mode = render_mode
        self.obs_source = obs
        self._poses = {a.name: stable_poses(a) for a in self.assets}
        self._clutter_pool = load_objects("train") if clutter else ()
        if obs == "render":
            from sim.render import RenderObserver  # EGL is only touched when asked for

            self.observer = RenderObserver()
        else:
            self.observer = MeshObserver()
        n = n_obj + n_bg
        self.observation_space = spaces.Dict(
            {
                # metres; bounds far outside the bin (an object that leaves it ends the episode)
                "points": spaces.Box(-10.0, 10.0, (n, 3), np.float32),
                "features": spaces.Box(-20.0, 20.0, (n, FEATURE_DIM), np.float32),
                "normals": spaces.Box(-1.0, 1.0, (n_obj, 3), np.float32),
            }
        )
        self.action_space = spaces.Tuple((spaces.Discrete(n_obj), spaces.Box(-1.0, 1.0, (3,), np.float32)))
        self._scenes: dict[tuple[str, ...], BinScene] = {}
        self.scene: BinScene | None = None
        self._obs: dict[str, np.ndarray] | None = None
        self._renderer = None

    # --- helpers ---------------------------------------------------------------------------------
    def _get_scene(self, asset: ObjectAsset, clutter: tuple[ObjectAsset, ...]) -> BinScene:
        key = (asset.name, *(c.name for c in clutter))
        if key not in self._scenes:
            if len(self._scenes) > 64:  # clutter makes many combinations: keep memory bounded
                self._scenes.clear()
            obstacles = self.task.obstacles if self.task else ()
            self._scenes[key] = BinScene(asset, clutter, obstacles, contacts=self.contacts)
        return self._scenes[key]

    def _refresh_goal(self) -> None:
        """The goal the flow, reward and success use: the nearest pose that looks like ``T_goal``."""
        asset = self.scene.asset
        T_obj = self.scene.object_T()
        key = (asset.name, T_obj.tobytes(), self.T_goal.tobytes())
        if key == self._goal_key:  # evaluated and observed in the same state: pick once
            return
        self._goal_key = key
        if asset.name not in self._symmetries:
            self._symmetries[asset.name] = (
                symmetries(asset) if self.goal_symmetry == "object" else np.eye(4)[None]
            )
        goal_key = (asset.name, self.T_goal.tobytes())
        if self._goal_poses is None or self._goal_poses[0] != goal_key:  # a new goal: once an episode
            poses = SymmetricGoals(self.T_goal, asset.surface_points, self._symmetries[asset.name])
            self._goal_poses = (goal_key, poses)
        self.T_goal_eff = self._goal_poses[1].nearest(T_obj, self.scene.object_surface())

    def _observe(self) -> dict[str, np.ndarray]:
        self._refresh_goal()
        obj_p, obj_n, bg = self.observer.segmented_clouds(self.scene)
        obs = build_observation(
            obj_p, obj_n, bg, self.scene.object_T(), self.T_goal_eff, self.n_obj, self.n_bg, self.np_random
        )
        self._obs = obs
        return obs

    def _evaluate(self) -> tuple[float, bool, float]:
        """Reward, success and distance at the current pose."""
        self._refresh_goal()
        T_obj = self.scene.object_T()
        return reward_and_success(self.scene.object_surface(), T_obj, self.T_goal_eff)

    def _place_clutter(self, rng, obj_pos, obj_r) -> None:
        placed = [(obj_pos[:2], obj_r)]
        for i, c in enumerate(self.scene.clutter):
            poses = stable_poses(c)
            for _ in range(50):
                pos, quat = sample_placement(c, poses[rng.integers(len(poses))], rng)
                r = footprint_radius(c, quat)
                if all(np.linalg.norm(pos[:2] - p) > r + q + 0.01 for p, q in placed):
                    break
            placed.append((pos[:2], r))
            self.scene.set_object_pose(pos, quat, body=f"clutter{i}")

    # --- gymnasium API ---------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        options = options or {}
        if self.task is not None:
            return self._reset_task(rng)
        if "object" in options:
            by_name = {a.name: a for a in self.assets}
            asset = by_name[options["object"]]
        else:
            asset = sample_object(self.assets, rng)
        clutter = tuple(
            self._clutter_pool[rng.integers(len(self._clutter_pool))] for _ in range(self.n_clutter)
        )
        self.scene = self._get_scene(asset, clutter)
        self.scene.reset()  # full reset: MuJoCo's warm-start state must not leak between episodes
        # the start and goal: sim.goals, shared with the deploy twin (same draws, same order)
        poses = self._poses[asset.name]
        # flip_share (training only): this episode's goal is a flip with that probability. None keeps
        # the natural draw, and the rng stream with it (evaluation episodes stay the same episodes)
        flip = None if self.flip_share is None else bool(rng.random() < self.flip_share)
        if flip and not self._flippable(asset, poses):
            flip = None  # no stable pose is a flip from another (a cube): draw as without flip_share
        (pos, quat), (gpos, gquat) = sample_start_and_goal(
            asset, self.goal_mode, rng, poses, symmetric=self.goal_symmetry == "object", flip=flip
        )
        self.T_goal = pose_matrix(gpos, gquat)
        self.scene.set_object_pose(pos, quat)
        if clutter:
            self._place_clutter(rng, pos, footprint_radius(asset, quat))
        self.scene.set_goal_ghost(gpos, gquat)
        self.scene.settle(max_s=0.5)
        self.goal_pose = (gpos, gquat)
        self._steps = 0
        _, _, dist = self._evaluate()
        info = {
            "object": asset.name,
            "distance": dist,
            "success": False,
            "goal_tilt_deg": self._goal_tilt_deg(),
        }
        return self._observe(), info

    def _flippable(self, asset, poses: np.ndarray) -> bool:
        """:func:`sim.goals.can_flip`, once per object."""
        if asset.name not in self._can_flip:
            self._can_flip[asset.name] = can_flip(asset, poses, symmetric=self.goal_symmetry == "object")
        return self._can_flip[asset.name]

    def _goal_tilt_deg(self) -> float:
        """Degrees between the object's up direction now and at the goal (up to its symmetry): ~0 when
        the goal only moves and yaws it, ~90 or ~180 when the goal lies on another face (a flip)."""
        return tilt_deg(self.scene.object_T(), self.T_goal_eff, self._symmetries[self.scene.asset.name])

    def _reset_task(self, rng):
        """A task's start (fixed, or random in its start region) and goal; see ``sim.tasks``."""
        self.scene = self._get_scene(self.assets[0], ())
        self.scene.reset()
        pos, quat = self.task.start_pose(rng if self.task_start == "random" else None)
        self.scene.set_object_pose(pos, quat)
        self.scene.settle(max_s=0.5)
        self._set_task_goal()
        self._steps = 0
        self._trajectory = []
        _, _, dist = self._evaluate()
        info = {"object": self.scene.asset.name, "distance": dist, "success": False}
        return self._observe(), {**info, "goal_tilt_deg": self._goal_tilt_deg()}

    def _set_task_goal(self) -> None:
        gpos, gquat = self.task.goal(*self.scene.object_pose())
        self.T_goal = pose_matrix(gpos, gquat)
        self.scene.set_goal_ghost(gpos, gquat)
        self.goal_pose = (gpos, gquat)

    def step(self, action):
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        index, motion = action
        index = int(index)
        motion = np.asarray(motion, dtype=np.float64).reshape(3)
        if not 0 <= index < self.n_obj:
            raise ValueError(f"action index must be in [0, {self.n_obj}), got {index}")
        if not np.all(np.isfinite(motion)):
            raise ValueError("action motion contains NaN or inf")
        point = self._obs["points"][index]
        normal = self._obs["normals"][index]
        pose_before = np.concatenate(self.scene.object_pose())
        waypoints = primitive_waypoints(point, normal, motion)
        rejected, reason, steps, force_stopped = False, "", 0, False
        try:
            check_plan(waypoints, SIM_WORKSPACE)
        except PrimitiveRejected as e:
            rejected, reason = True, str(e)
        if not rejected:
            result = self.scene.execute_primitive(waypoints)
            rejected, reason, steps = not result.executed, result.reason, result.physics_steps
            force_stopped = result.force_stopped
        self._steps += 1
        if self.task is not None:
            self._trajectory.append(
                TaskStep(
                    point.copy(),
                    motion.copy(),
                    not rejected,
                    pose_before,
                    np.concatenate(self.scene.object_pose()),
                )
            )
            if self.task.goal_follows_object:
                self._set_task_goal()
        reward, success, dist = self._evaluate()
        pose_after = np.concatenate(self.scene.object_pose())
        idle = not rejected and (
            np.linalg.norm(pose_after[:3] - pose_before[:3]) < IDLE_MOVE_M
            and quat_angle(pose_before[3:], pose_after[3:]) < IDLE_TURN_RAD
        )
        left_bin = not self.scene.object_in_bin()
        terminated = bool(success or left_bin)
        truncated = bool(not terminated and self._steps >= self.max_steps)
        info = {
            "reward_flow": reward,
            "distance": dist,
            "success": bool(success),
            "rejected": rejected,
            "reject_reason": reason,
            "failure": "object_left_bin" if left_bin else ("timeout" if truncated else ""),
            "object": self.scene.asset.name,
            "physics_steps": steps,
            "force_stopped": force_stopped,  # the hand passed the contact-force stop and let go there
            "idle": bool(idle),  # it ran and left the object where it was (IDLE_MOVE_M, IDLE_TURN_RAD)
            "goal_tilt_deg": self._goal_tilt_deg(),  # the tilt still left to the goal (reset's: at the start)
            "waypoints": waypoints,
            # poses after the primitive, position (3,) m + quaternion wxyz (4,): hindsight relabelling
            # (models.replay) turns what the object reached into a goal
            "object_pose": pose_after,
            "goal_pose": np.concatenate(self.goal_pose),
        }
        if terminated or truncated:
            # where the episode ended, split into placing and turning (once an episode: not per step)
            split = flow_split(self.scene.object_surface(), self.scene.object_T(), self.T_goal_eff)
            info["final_position_m"], info["final_rotation_m"] = split
            if self.task is not None:
                info["behaviour"] = self.task.behaviour(self._trajectory)
        return self._observe(), float(reward), terminated, truncated, info

    def get_sim_state(self) -> dict:
        """A snapshot of everything ``step`` depends on (physics, last observation, goal, primitive
        count): with ``set_sim_state`` a planner can try pushes and go back (``bench/lookahead.py``)."""
        if self._obs is None:
            raise RuntimeError("call reset() before get_sim_state()")
        return {
            "scene": self.scene,
            "physics": self.scene.get_state(),
            "obs": {k: v.copy() for k, v in self._obs.items()},
            "steps": self._steps,
            "T_goal": self.T_goal.copy(),
            "goal_pose": self.goal_pose,
            "trajectory": list(getattr(self, "_trajectory", [])),
        }

    def set_sim_state(self, snapshot: dict) -> None:
        """Return to a ``get_sim_state`` snapshot taken in this episode (same scene)."""
        if snapshot["scene"] is not self.scene:
            raise ValueError("the snapshot belongs to another episode's scene: take it after this reset()")
        self.scene.set_state(snapshot["physics"])
        self._obs = {k: v.copy() for k, v in snapshot["obs"].items()}
        self._steps, self.goal_pose = snapshot["steps"], snapshot["goal_pose"]
        self.T_goal = snapshot["T_goal"].copy()
        self._refresh_goal()
        self.scene.set_goal_ghost(*self.goal_pose)
        if self.task is not None:
            self._trajectory = list(snapshot["trajectory"])

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from sim.render import render_rgb

        return render_rgb(self)

    def close(self):
        getattr(self.observer, "close", lambda: None)()
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


if "hydo/Bin-v0" not in gym.registry:
    gym.register(id="hydo/Bin-v0", entry_point="sim.env:BinEnv", disable_env_checker=True)
