"""The deploy loop: observe → register → decide (ONNX) → check → execute → repeat. Strictly in sequence:
perception and the policy never run while the arm moves.

Start-up, in this order, so that nothing opens or moves on bad input: cell file → model folder
(``OnnxPolicy.load`` checks every hash before any device opens) → goal and background files →
realtime kernel (real arms) → cameras (serials, USB) → robot (connect, recover, limits) → one
warm-up decision. Per step::

    frames  = cameras, fresh (newer than the last motion), arm at home        CameraError
    seg     = perception.segment(frames, background)                          PerceptionError
    reg     = registration.register(seg.obj_points, goal.points)              RegistrationError
    success = reg.distance < 3 cm                                              (episode ends)
    obs     = build_observation(..., T_goal = reg.T)  ->  gate.check_observation
    action  = policy.act(obs)                         ->  gate.check_action   InputError
    plan    = gate.plan_primitive(point, normal, motion)                      PrimitiveRejected,
                                                                              UnreachableError
    log the step (frames, masks, clouds, obs, action, plan); --dry-run prints the plan and stops here
    result  = robot.execute(plan)        every command logged (fsynced) before it is sent
    ok -> next step;  reaction_fired / short_of_goal -> checked retract, next step (an outcome of
    the step, not a failure of the run);  reflex -> one recovery decided by the robot mode, checked
    retract, re-observe (robot-safety.md: at most once per primitive and three times per episode; a
    reflex beyond that, i.e. one during the retract or the fourth in an episode, stops the run);
    comm_lost / critical -> stop the run with what the person must do.

A refusal (perception, registration, input, plan) stops the run on a real arm; in the twin
(``--robot sim``) it ends the episode by default, so that an evaluation over many episodes
survives a bad decision (``on_refusal``). Either way it is logged and reported in one line. The
same default applies in the twin to a reflex beyond the recovery limits (``RecoveryLimitError``):
a real arm stops the run there, the twin ends the episode and resets its arm for the next one
(``--on-refusal stop`` makes the twin stop the run like a real arm).
"""

from __future__ import annotations

import contextlib
import json
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from robot.cameras import CameraSet, ReplayExhausted, open_cameras
from robot.cell import load_cell
from robot.errors import (
    CameraError,
    InputError,
    PerceptionError,
    RecoveryLimitError,
    RegistrationError,
    RobotConnectionError,
    RobotError,
    RobotFaultError,
    UnreachableError,
)
from robot.executor import Outcome, RobotMode, make_executor, operator_action
from robot.onnx_policy import OnnxPolicy
from robot.perception import Background, capture_background, observation, segment
from robot.registration import Goal, check_registration, goal_from_offset, register
from robot.safety import RecoveryBudget, SafetyGate, check_realtime
from robot.session_log import SessionLog
from sim.contract import MAX_PRIMITIVES, SUCCESS_THRESHOLD_M, transform_points
from sim.primitive import PrimitiveRejected

ROBOTS = ("panda", "fr3", "sim")
#: Refusals: bad input that stops nothing physical. Robot and camera failures are never refusals.
REFUSALS = (PerceptionError, RegistrationError, InputError, PrimitiveRejected, UnreachableError)
RECAPTURE_WAIT_S = 0.5


@dataclass
class DeployConfig:
    """Everything ``hydo deploy`` was asked to do (one field per flag)."""

    robot: str  # panda | fr3 | sim
    model: Path
    cell: Path | None = None  # None: the shipped example cell (the twin's)
    goal: Path | None = None  # goal.npz; None with --robot sim: sampled per episode like training
    goal_offset: tuple[float, float, float] | None = None  # (dx m, dy m, yaw deg) from the start cloud
    background: Path | None = None  # None: BACKGROUND next to the cell file (sim: captured at start)
    episodes: int = 1
    max_steps: int = MAX_PRIMITIVES
    log_dir: Path | None = None  # session folder; None: runs/deploy/<time>-<robot>
    dry_run: bool = False
    seed: int = 0
    allow_no_realtime: bool = False
    on_refusal: str | None = None  # "stop" | "next-episode"; None: stop on arms, next-episode in sim
    # (in sim it also decides what a reflex beyond the recovery limits does; real arms always stop)
    replay: Path | None = None  # play a recorded session's frames back (implies --dry-run)
    objects: str | None = None  # twin only: object set (default: the model's training objects)
    speed_scale: float = 1.0  # in (0, 1]: every command slower than the cell's speeds by this factor
    command: str = ""

    def resolved_on_refusal(self) -> str:
        if self.on_refusal is not None:
            return self.on_refusal
        return "next-episode" if self.robot == "sim" and self.replay is None else "stop"


@dataclass
class StepRecord:
    episode: int
    step: int
    distance: float  # m, measured by registration
    rmse: float
    inliers: float
    n_object_points: int
    outcome: str = ""  # the plan's outcome, "dry-run", "success" or the refusal class
    seconds: float = 0.0  # wall time of the whole step
    perception_s: float = 0.0
    registration_s: float = 0.0
    policy_s: float = 0.0
    execution_s: float = 0.0
    iou: float | None = None  # twin: mask IoU vs ground truth (pooled over cameras)
    registration_error: float | None = None  # twin: ADD-S (m) of the estimated vs true transform
    true_distance: float | None = None  # twin: mean goal flow from the true poses (training's)


@dataclass
class EpisodeResult:
    episode: int
    success: bool  # measured (registration distance < 3 cm)
    steps: int  # primitives executed (or planned, in a dry run)
    distance: float | None  # last measured distance, m
    reason: str = ""  # why it ended without success
    object: str = ""
    true_success: bool | None = None  # twin: from the true poses
    true_distance: float | None = None


@dataclass
class SessionResult:
    folder: Path
    episodes: list[EpisodeResult] = field(default_factory=list)
    steps: list[StepRecord] = field(default_factory=list)
    commands_sent: int = 0
    force_stops: int = 0  # contact-force stops (reaction_fired): an outcome of a step
    reflexes: int = 0  # robot reflexes, each recovered once or ending the run
    reflex_limit_episodes: int = 0  # twin: episodes ended by the recovery limits (a real arm stops)

    def summary(self) -> dict:
        def mean(xs):
            xs = [x for x in xs if x is not None]
            return float(np.mean(xs)) if xs else None

        eps = self.episodes
        # time per step: the steps that planned a primitive (not the episodes' final observations)
        timed = [s for s in self.steps if s.policy_s > 0]
        return {
            "episodes": len(eps),
            "success_rate": mean([float(e.success) for e in eps]),
            "true_success_rate": mean(
                [None if e.true_success is None else float(e.true_success) for e in eps]
            ),
            "primitives": sum(e.steps for e in eps),
            "mean_iou": mean([s.iou for s in self.steps]),
            "mean_registration_error_m": mean([s.registration_error for s in self.steps]),
            "mean_registration_rmse_m": mean([s.rmse for s in self.steps]),
            "mean_step_s": mean([s.seconds for s in timed]),
            "mean_perception_s": mean([s.perception_s for s in self.steps]),
            "mean_registration_s": mean([s.registration_s for s in self.steps]),
            "mean_policy_s": mean([s.policy_s for s in timed]),
            "mean_execution_s": mean([s.execution_s for s in timed if s.execution_s > 0]),
            "commands_sent": self.commands_sent,
            "force_stops": self.force_stops,
            "reflexes": self.reflexes,
            "reflex_limit_episodes": self.reflex_limit_episodes,
        }


def default_session_folder(robot: str) -> Path:
    return Path("runs") / "deploy" / f"{time.strftime('%Y%m%d-%H%M%S')}-{robot}"


def _versions() -> dict:
    import importlib.metadata as md

    out = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in (
        "hydo",
        "numpy",
        "onnxruntime",
        "mujoco",
        "opencv-python-headless",
        "panda-python",
        "franky-control",
        "pyrealsense2",
    ):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    return out


class Deployment:
    """One ``hydo deploy`` run. Build with :meth:`prepare`, then :meth:`run` (returns the results).

    Tests inject ``cameras`` (a ``CameraSet``), an ``executor`` and a ``world``; the CLI lets
    ``prepare`` build them from the configuration.
    """

    def __init__(self, cfg: DeployConfig, cell, policy: OnnxPolicy, log: SessionLog, printer=None):
        self.cfg = cfg
        self.cell = cell
        self.policy = policy
        self.log = log
        self.print = printer or (lambda *a, **k: None)
        self.rng = np.random.default_rng(cfg.seed)
        self.world = None
        self.gate: SafetyGate | None = None
        self.background: Background | None = None
        self.goal: Goal | None = None
        self.goal_mode = str(policy.manifest.get("goals", "6d"))
        self.budget = RecoveryBudget()
        self.result = SessionResult(log.folder)
        self.on_plan = None  # dry-run hook: called with (episode, step, plan)
        self._true_goal_T = None

    # --- start-up -----------------------------------------------------------------------------------
    @classmethod
    def prepare(cls, cfg: DeployConfig, printer=None) -> Deployment:
        """Load and check every file before any device opens; create the session folder."""
        if cfg.robot not in ROBOTS:
            raise ValueError(f"`--robot` must be one of {list(ROBOTS)}. Got {cfg.robot!r}.")
        cell = load_cell(cfg.cell)
        policy = OnnxPolicy.load(cfg.model)
        goal = Goal.load(cfg.goal) if cfg.goal is not None else None
        if cfg.replay is not None and goal is None:
            replay_goal = Path(cfg.replay) / "goals" / "e000.npz"
            goal = Goal.load(replay_goal) if replay_goal.exists() else None
        real = cfg.robot != "sim" and cfg.replay is None
        if real and goal is None and cfg.goal_offset is None:
            raise RegistrationError(
                "a real arm needs a goal: --goal goal.npz (from `hydo deploy capture-goal`) or --goal-offset DX,DY[,YAW]"
            )
        if cfg.replay is not None and goal is None and cfg.goal_offset is None:
            raise RegistrationError(
                f"replay: {cfg.replay} has no goals/e000.npz; pass --goal or --goal-offset"
            )
        background = None
        bg_path = cfg.background
        if cfg.replay is not None and bg_path is None:
            bg_path = Path(cfg.replay) / "background.npz"
        if bg_path is None and cfg.robot != "sim":
            bg_path = Path(cell.source).with_name("background.npz")
        if bg_path is not None:
            background = Background.load(bg_path, cell)
        folder = Path(cfg.log_dir) if cfg.log_dir is not None else default_session_folder(cfg.robot)
        try:
            log = SessionLog(folder)
        except FileExistsError as e:
            raise RobotError(str(e)) from None
        dep = cls(cfg, cell, policy, log, printer)
        dep.background = background
        dep.goal = goal
        log.write_json(
            "session.json",
            {
                "command": cfg.command,
                "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
                "robot": cfg.robot,
                "model": str(cfg.model),
                "manifest": {k: v for k, v in policy.manifest.items() if k != "agent_config"},
                "cell": cell.summary(),
                "versions": _versions(),
                "started_at": time.time(),
            },
        )
        with contextlib.suppress(OSError):
            (log.folder / "cell.yaml").write_text(Path(cell.source).read_text())
        if background is not None:
            background.save(log.folder / "background.npz")
        log.event("start", robot=cfg.robot, dry_run=cfg.dry_run, model=str(cfg.model), cell=cell.source)
        return dep

    def _warm_up(self) -> float:
        """One decision on a dummy observation (onnxruntime's first run is slow); returns seconds."""
        p = self.policy
        n = p.n_obj + p.n_bg
        pts = self.rng.uniform(-0.1, 0.1, (n, 3)).astype(np.float32)
        feats = np.zeros((n, 4), np.float32)
        feats[: p.n_obj, 0] = 1.0
        normals = np.tile(np.float32([0.0, 0.0, 1.0]), (p.n_obj, 1))
        t = time.perf_counter()
        p.act(pts, feats, np.random.default_rng(0), normals=normals)
        return time.perf_counter() - t

    # --- the run ------------------------------------------------------------------------------------
    def run(self, cameras: CameraSet | None = None, executor=None, world=None) -> SessionResult:
        """Open devices (unless given), run every episode, close everything; returns the results."""
        cfg, cell = self.cfg, self.cell
        real_arm = cfg.robot != "sim"
        try:
            if cfg.robot == "sim" and world is None and cfg.replay is None:
                from robot.twin import TwinWorld

                world = TwinWorld(cell, robot_type="panda", seed=cfg.seed)
            self.world = world
            self.gate = SafetyGate(cell, world.kin if world is not None and world.model is not None else None)
            assets = self._twin_assets() if world is not None else ()
            if world is not None and world.model is None:
                world.load(assets[0])
                self.gate = SafetyGate(cell, world.kin)
            if real_arm and not cfg.dry_run and cfg.replay is None:
                check_realtime(cfg.allow_no_realtime, self.log)
            if cameras is None:
                cameras = open_cameras(cell, cfg.robot, world=world, replay=cfg.replay)
            dry = cfg.dry_run or cfg.replay is not None
            if executor is None and not dry:
                executor = make_executor(
                    cfg.robot,
                    cell,
                    log=self.log,
                    world=world,
                    allow_no_realtime=cfg.allow_no_realtime,
                    speed_scale=cfg.speed_scale,
                )
            if executor is not None:
                if executor.log is None:
                    executor.log = self.log
                executor.speed_scale = min(executor.speed_scale, cfg.speed_scale)
            with cameras, executor if executor is not None and not dry else contextlib.nullcontext() as robot:
                warm = self._warm_up()
                self.log.event("warm_up", policy_s=round(warm, 4))
                if self.background is None:
                    self.background = self._capture_background(cameras)
                for ep in range(cfg.episodes):
                    try:
                        self.result.episodes.append(self._episode(ep, cameras, robot, assets))
                    except ReplayExhausted as e:  # every recorded frame played: the replay is over
                        self.log.event("replay_end", message=str(e))
                        self.print(str(e))
                        break
            self.log.event("done", summary=self.result.summary())
        except KeyboardInterrupt:
            self.log.event("interrupted", note="Ctrl-C: arm stopped, cameras closed")
            raise
        except RobotError as e:
            self.log.event("stopped", error=e.__class__.__name__, message=str(e))
            raise
        finally:
            if executor is not None:
                self.result.commands_sent = executor.commands_sent
            self.log.close()
            if world is not None:
                world.close()
        return self.result

    def _twin_assets(self):
        from sim.objects import load_objects

        spec = self.cfg.objects or str(self.policy.manifest.get("objects") or "train")
        return load_objects(spec)

    def _capture_background(self, cameras) -> Background:
        """Twin only: the empty bin, arm at home (real arms use ``hydo deploy capture-background``)."""
        w = self.world
        if w is None:
            raise PerceptionError("no background: run `hydo deploy capture-background` first")
        w.reset_arm()
        w.hide_object()
        bg = capture_background(cameras, self.cell)
        bg.save(self.log.folder / "background.npz")
        self.log.event("background_captured", frames=self.cell.perception.background_frames)
        return bg

    # --- one episode --------------------------------------------------------------------------------
    def _episode(self, ep: int, cameras, robot, assets) -> EpisodeResult:
        cfg = self.cfg
        self.budget.new_episode()
        obj_name = ""
        if self.world is not None:
            obj_name = self._twin_episode(ep, cameras, assets)
        goal = self.goal
        self.log.event("episode_start", episode=ep, object=obj_name)
        last_distance = None
        primitives = 0
        for step in range(cfg.max_steps + 1):
            self.budget.new_primitive()
            t_step = time.perf_counter()
            frames, saved, rec = None, False, None
            try:
                frames = self._capture(cameras, robot)
                t0 = time.perf_counter()
                seg = segment(frames, self.background, self.cell, self.rng)
                t_perc = time.perf_counter() - t0
                if goal is None:  # --goal-offset: the goal is the first cloud of the episode, moved
                    goal = goal_from_offset(seg.obj_points, *cfg.goal_offset)
                    goal.save(self.log.folder / "goals" / f"e{ep:03d}.npz")
                    self.log.event("goal_from_offset", episode=ep, offset=list(cfg.goal_offset))
                reg = register(seg.obj_points, goal.points, self.goal_mode, seed=cfg.seed + step)
                rec = StepRecord(
                    ep,
                    step,
                    reg.distance,
                    reg.rmse,
                    reg.inlier_fraction,
                    len(seg.obj_points),
                    perception_s=t_perc,
                    registration_s=reg.seconds,
                )
                self._twin_metrics(rec, seg, reg)
                self.log.event(
                    "observation",
                    episode=ep,
                    step=step,
                    registration=reg.to_json(),
                    n_object_points=len(seg.obj_points),
                    mismatch=seg.mismatch,
                    iou=rec.iou,
                    registration_error_m=rec.registration_error,
                    true_distance_m=rec.true_distance,
                )
                check_registration(
                    reg,
                    self.cell.perception.registration_max_rmse,
                    self.cell.perception.registration_min_inliers,
                )
                last_distance = reg.distance
                if reg.distance < SUCCESS_THRESHOLD_M or step == cfg.max_steps:
                    self._save_step(ep, step, frames, seg, None, None, None, reg)
                    saved = True
                    rec.outcome = "success" if reg.distance < SUCCESS_THRESHOLD_M else "step_limit"
                    rec.seconds = time.perf_counter() - t_step
                    self.result.steps.append(rec)
                    break
                obs = observation(seg, reg.T, self.policy.n_obj, self.policy.n_bg, self.rng)
                self.gate.check_observation(obs, self.policy.n_obj, self.policy.n_bg)
                t0 = time.perf_counter()
                # choose among points whose push can start clear of the cloud and the bin (as in
                # training); the gate below still checks the chosen plan in full
                index, motion, _ = self.policy.act(
                    obs["points"],
                    obs["features"],
                    self.rng,
                    normals=obs["normals"],
                    workspace=self.cell.workspace,
                    bin_box=(self.cell.bin_low, self.cell.bin_high),
                )
                rec.policy_s = time.perf_counter() - t0
                self.gate.check_action(index, motion, self.policy.n_obj)
                point, normal = obs["points"][index], obs["normals"][index]
                plan = None
                try:
                    plan = self.gate.plan_primitive(point, normal, motion)
                finally:  # the step is logged whether or not its plan passed the gate
                    self._save_step(ep, step, frames, seg, obs, (index, motion), plan, reg)
                    saved = True
                self.log.event(
                    "plan",
                    episode=ep,
                    step=step,
                    index=int(index),
                    motion=np.round(motion, 5).tolist(),
                    point=np.round(point, 5).tolist(),
                    normal=np.round(normal, 5).tolist(),
                    waypoints=np.round(plan.waypoints, 5).tolist(),
                    commands=[c.to_json() for c in plan.commands],
                    min_joint_margin_rad=round(plan.min_joint_margin, 4),
                )
            except REFUSALS as e:
                if frames is not None and not saved:  # the capture is logged even when it is refused
                    self.log.save_step(ep, step, frames)
                if rec is not None:
                    rec.outcome = e.__class__.__name__
                    rec.seconds = time.perf_counter() - t_step
                    self.result.steps.append(rec)
                self.log.event("refused", episode=ep, step=step, error=e.__class__.__name__, message=str(e))
                if self.cfg.resolved_on_refusal() == "stop":
                    raise
                self.print(f"episode {ep}: step {step} refused ({e.__class__.__name__}): {e}")
                return self._end_episode(ep, False, primitives, last_distance, f"refused: {e}", obj_name)
            if self.on_plan is not None:
                self.on_plan(ep, step, plan)
            if robot is None:  # --dry-run / --replay: the plan was checked and printed; nothing moves
                rec.outcome = "dry-run"
                rec.seconds = time.perf_counter() - t_step
                self.result.steps.append(rec)
                primitives += 1
                continue
            t0 = time.perf_counter()
            result = robot.execute(plan)
            rec.execution_s = time.perf_counter() - t0
            self.log.event("outcome", episode=ep, step=step, **result.to_json())
            rec.outcome = result.outcome.value
            primitives += 1
            if result.outcome is not Outcome.ok:
                try:
                    self._handle_failure(result, robot)
                except RecoveryLimitError as e:
                    if self.world is None or self.cfg.resolved_on_refusal() == "stop":
                        raise  # a real arm (or --on-refusal stop): the run stops, a person inspects the cell
                    # The twin's evaluation: the episode ends here and the next one starts with the arm
                    # reset at home (a twin-only step; a real arm stops the run at this point).
                    self.log.event(
                        "episode_stopped", episode=ep, step=step, error=e.__class__.__name__, message=str(e)
                    )
                    self.print(f"episode {ep}: {e} (twin: next episode; a real arm stops the run here)")
                    rec.seconds = time.perf_counter() - t_step
                    self.result.steps.append(rec)
                    self.result.reflex_limit_episodes += 1
                    return self._end_episode(
                        ep, False, primitives, last_distance, f"reflex limit: {e}", obj_name
                    )
            if self.world is not None:
                self.world.settle_object()
            rec.seconds = time.perf_counter() - t_step
            self.result.steps.append(rec)
            if self.world is not None and not self.world.object_in_bin():
                return self._end_episode(
                    ep, False, primitives, last_distance, "object left the bin", obj_name
                )
        success = last_distance is not None and last_distance < SUCCESS_THRESHOLD_M
        return self._end_episode(
            ep, success, primitives, last_distance, "" if success else "step limit", obj_name
        )

    def _end_episode(self, ep, success, steps, distance, reason, obj_name) -> EpisodeResult:
        res = EpisodeResult(ep, bool(success), steps, distance, reason, obj_name)
        if self.world is not None and self._true_goal_T is not None:
            d = self._true_distance()
            res.true_distance, res.true_success = d, bool(d < SUCCESS_THRESHOLD_M)
        self.log.event("episode_end", **asdict(res))
        dist = "n/a" if distance is None else f"{distance * 100:.1f} cm"
        self.print(
            f"episode {ep}: {'success' if success else 'no success'} after {steps} primitives, distance {dist}"
            + (f" ({reason})" if reason and not success else "")
        )
        return res

    # --- observation helpers ------------------------------------------------------------------------
    def _capture(self, cameras: CameraSet, robot) -> list:
        """Fresh frames with the arm at home: a stale frame or an arm away from home is discarded and
        re-captured once, then refused."""
        max_age = self.cell.perception.max_frame_age
        for attempt in range(2):
            if robot is not None and not robot.at_home():
                problem = (
                    "the arm is not at its home pose (cell robot.home_joints; it may be in the cameras' view): "
                    "move it there first"
                )
            else:
                frames = cameras.capture()
                now = time.time()
                motion_end = robot.last_motion_end if robot is not None else 0.0
                stale = [f for f in frames if f.timestamp <= motion_end or now - f.timestamp > max_age]
                if not stale:
                    return frames
                problem = f"camera {stale[0].serial} delivered a stale frame (older than the last motion or {max_age:g} s)"
            self.log.event("frame_discarded", attempt=attempt, reason=problem)
            if attempt == 0:
                time.sleep(RECAPTURE_WAIT_S if self.world is None else 0.0)
        raise CameraError(f"{problem}; refused after one re-capture")

    def _save_step(self, ep, step, frames, seg, obs, action, plan, reg) -> None:
        arrays = {
            "obj_points": seg.obj_points,
            "obj_normals": seg.obj_normals,
            "bg_points": seg.bg_points,
            "registration_T": reg.T,
        }
        for f, m in zip(frames, seg.masks, strict=True):
            arrays[f"mask/{f.serial}"] = m
        if obs is not None:
            arrays.update({"points": obs["points"], "features": obs["features"], "normals": obs["normals"]})
        if action is not None:
            arrays["action_index"] = np.array(action[0])
            arrays["action_motion"] = np.asarray(action[1])
        if plan is not None:
            arrays["waypoints"] = plan.waypoints
            arrays["command_targets"] = np.array([c.target for c in plan.commands])
        self.log.save_step(ep, step, frames, **arrays)

    # --- recovery -----------------------------------------------------------------------------------
    def _handle_failure(self, result, robot) -> None:
        """Stop, recover or retract after a plan that did not end ``ok`` (robot-safety.md's rules)."""
        where = result.failed.label if result.failed is not None else "?"
        if result.outcome is Outcome.comm_lost:
            raise RobotConnectionError(
                f"connection to the {robot.name} robot lost during '{where}' ({result.message}); not reconnecting: "
                f"check the network and the arm, then re-run (the log's last command is '{where}')"
            )
        if result.outcome is Outcome.critical:
            raise RobotFaultError(
                f"the {robot.name} robot stopped with {list(result.errors) or result.robot_mode} during '{where}': "
                f"{operator_action(result.errors)}. Not recovered automatically."
            )
        if result.outcome is Outcome.reflex:
            self.result.reflexes += 1
            mode = robot.robot_mode()
            errors = tuple(result.errors) or robot.current_errors()
            self.budget.authorise(mode, errors, where)  # raises RobotFaultError when not allowed
            self.log.event(
                "recovery",
                mode=mode.value,
                errors=list(errors),
                during=where,
                recoveries_this_episode=self.budget.episode,
            )
            self.print(f"reflex ({', '.join(errors) or mode.value}) during '{where}': recovering")
            if mode is RobotMode.reflex or errors:  # decided from the mode: flags may clear while it latches
                robot.recover()
            if robot.robot_mode() is RobotMode.reflex:
                robot.recover()
                if robot.robot_mode() is RobotMode.reflex:
                    raise RobotFaultError(
                        "the robot stays in reflex mode after recovery: clear it in Desk, then re-run"
                    )
        elif result.outcome is Outcome.reaction_fired:
            self.result.force_stops += 1
            self.log.event("force_stop", during=where, peak_force_n=result.peak_force)
            self.print(f"contact-force stop during '{where}' ({result.message}): retracting")
        # Never resume the old waypoints: retract along a checked path, then re-observe and re-plan.
        retract = self.gate.plan_retract(robot.fingertip(), robot.joints())
        self.log.event("retract", commands=[c.to_json() for c in retract.commands])
        r = robot.execute(retract)
        self.log.event("retract_outcome", **r.to_json())
        if r.outcome is Outcome.reflex:
            self._handle_failure(r, robot)  # counts against the same budget; retracts again
        elif r.outcome is not Outcome.ok:
            raise RobotFaultError(
                f"the retract after '{where}' ended '{r.outcome.value}' ({r.message}): guide the arm home"
            )

    # --- the twin -----------------------------------------------------------------------------------
    def _twin_episode(self, ep: int, cameras, assets) -> str:
        """Place a start (and, without --goal, a goal captured through the cameras) in the twin."""
        from robot.twin import sample_episode

        w = self.world
        asset, start, goal_pose = sample_episode(w, assets, self.goal_mode, self.rng)
        if w.asset is not asset:
            w.load(asset)
            self.gate = SafetyGate(self.cell, w.kin)
        w.reset_arm()
        self._true_goal_T = None
        if self.cfg.goal is None and self.cfg.goal_offset is None:
            w.set_object_pose(*goal_pose)
            w.settle_object()
            self._true_goal_T = w.object_T()
            seg = segment(cameras.capture(), self.background, self.cell, self.rng)
            self.goal = Goal(seg.obj_points.copy(), "captured", None, time.time())
            self.goal.save(self.log.folder / "goals" / f"e{ep:03d}.npz")
        elif self.cfg.goal_offset is not None:
            self.goal = None  # made from the first observation
        w.set_object_pose(*start)
        w.settle_object()
        self.log.event(
            "twin_episode",
            episode=ep,
            object=asset.name,
            start=np.round(w.object_T(), 5).tolist(),
            goal=None if self._true_goal_T is None else np.round(self._true_goal_T, 5).tolist(),
        )
        return asset.name

    def _true_distance(self) -> float:
        w = self.world
        T_obj = w.object_T()
        surf = transform_points(T_obj, w.asset.surface_points)
        flow = transform_points(self._true_goal_T @ np.linalg.inv(T_obj), surf) - surf
        return float(np.linalg.norm(flow, axis=1).mean())

    def _twin_metrics(self, rec: StepRecord, seg, reg) -> None:
        w = self.world
        if w is None:
            return
        from robot.registration import adds_error
        from sim.render import mask_iou

        true = np.stack([w.true_mask(i) for i in range(len(self.cell.cameras))])
        rec.iou = mask_iou(np.stack(seg.masks), true)
        if self._true_goal_T is not None:
            T_obj = w.object_T()
            T_true = self._true_goal_T @ np.linalg.inv(T_obj)
            surf = transform_points(T_obj, w.asset.surface_points)
            rec.registration_error = adds_error(reg.T, T_true, surf)
            rec.true_distance = self._true_distance()


def summary_lines(res: SessionResult) -> list[tuple[str, str]]:
    """(name, value) rows of the final table."""
    s = res.summary()

    def pct(v):
        return "n/a" if v is None else f"{v:.0%}"

    def ms(v):
        return "n/a" if v is None else f"{v * 1000:.0f} ms"

    rows = [
        ("episodes", str(s["episodes"])),
        ("success rate (registration)", pct(s["success_rate"])),
    ]
    if s["true_success_rate"] is not None:
        rows.append(("success rate (twin, true poses)", pct(s["true_success_rate"])))
    rows.append(("primitives", str(s["primitives"])))
    if s["mean_iou"] is not None:
        rows.append(("segmentation IoU (twin)", f"{s['mean_iou']:.3f}"))
    if s["mean_registration_error_m"] is not None:
        rows.append(("registration error ADD-S (twin)", f"{s['mean_registration_error_m'] * 1000:.1f} mm"))
    if s["mean_registration_rmse_m"] is not None:
        rows.append(("registration inlier RMS", f"{s['mean_registration_rmse_m'] * 1000:.1f} mm"))
    rows += [
        ("time per step", "n/a" if s["mean_step_s"] is None else f"{s['mean_step_s']:.2f} s"),
        ("  perception", ms(s["mean_perception_s"])),
        ("  registration", ms(s["mean_registration_s"])),
        ("  policy (onnxruntime)", ms(s["mean_policy_s"])),
        ("  execution", "n/a" if s["mean_execution_s"] is None else f"{s['mean_execution_s']:.2f} s"),
        ("motion commands sent", str(s["commands_sent"])),
        ("contact-force stops", str(s["force_stops"])),
        ("reflexes", str(s["reflexes"])),
    ]
    if s["reflex_limit_episodes"]:
        rows.append(("episodes ended by the reflex limit (twin)", str(s["reflex_limit_episodes"])))
    rows += [
        ("session folder", str(res.folder)),
    ]
    return rows


def write_summary(res: SessionResult) -> None:
    (res.folder / "summary.json").write_text(json.dumps(res.summary(), indent=2))
