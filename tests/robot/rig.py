"""A scripted deploy rig for fault tests: half-resolution cell, synthetic frames, fake Panda.

``make_rig(tmp_path, model)`` writes ``cell.yaml`` (the example cell, cameras at 160x120),
``background.npz`` (the empty synthetic bin) and ``goal.npz`` (a 6 cm box at the goal) into
``tmp_path`` and returns a :class:`Rig` whose ``deployment()`` builds a ``robot.loop.Deployment``
on them. ``run()`` drives it with scripted cameras and ``PandaExecutor`` over a fake ``panda_py``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from fakes import Box, PandaScript, ScriptedCamera, SyntheticScene, fake_panda_py, install

from robot.cameras import CameraSet
from robot.cell import EXAMPLE_CELL, load_cell
from robot.loop import DeployConfig, Deployment
from robot.perception import capture_background, segment
from robot.registration import Goal

START = Box(xy=(0.52, 0.0))
GOAL = Box(xy=(0.62, 0.06))
SCALE = 0.5  # cameras at 160x120: 4x fewer rays to cast


def small_cell_dict() -> dict:
    data = copy.deepcopy(yaml.safe_load(EXAMPLE_CELL.read_text()))
    for cam in data["cameras"]:
        cam["width"], cam["height"] = int(cam["width"] * SCALE), int(cam["height"] * SCALE)
        k = cam["intrinsics"]
        k["fx"], k["fy"] = k["fx"] * SCALE, k["fy"] * SCALE
        k["cx"], k["cy"] = (k["cx"] + 0.5) * SCALE - 0.5, (k["cy"] + 0.5) * SCALE - 0.5
    data["perception"]["background_frames"] = 2
    data["perception"]["registration_max_rmse_m"] = 0.006  # sparser clouds at half resolution
    return data


@dataclass
class Rig:
    tmp: Path
    model: Path
    cell: object
    scene: SyntheticScene
    cams: list[ScriptedCamera] = field(default_factory=list)
    pp: object = None  # the fake panda_py module

    @property
    def cell_path(self) -> Path:
        return self.tmp / "cell.yaml"

    def deployment(self, **cfg) -> Deployment:
        kw = dict(
            robot="panda",
            model=self.model,
            cell=self.cell_path,
            goal=self.tmp / "goal.npz",
            log_dir=self.tmp / "session",
            allow_no_realtime=True,
            max_steps=1,
        )
        kw.update(cfg)
        return Deployment.prepare(DeployConfig(**kw))

    def cameras(self, script: list | None = None) -> CameraSet:
        """Fresh scripted cameras; ``script`` applies to the first camera (the others stay plain)."""
        self.cams = [
            ScriptedCamera(s, self.scene, script if i == 0 else None) for i, s in enumerate(self.cell.cameras)
        ]
        return CameraSet(self.cams)

    def robot(self, monkeypatch, script: PandaScript | None = None):
        from robot.panda import PandaExecutor

        self.pp = fake_panda_py(self.cell, script)
        install(monkeypatch, "panda_py", self.pp)
        return PandaExecutor(self.cell, allow_no_realtime=True)

    def run(self, monkeypatch, dep: Deployment, script: PandaScript | None = None, camera_script=None):
        """Run ``dep`` with scripted cameras and the fake Panda; returns the executor (and raises)."""
        executor = self.robot(monkeypatch, script)
        self._executor = executor
        dep.run(cameras=self.cameras(camera_script), executor=executor)
        return executor

    @property
    def arm(self):
        return None if self.pp is None else self.pp.arm

    def received(self) -> list:
        return [] if self.arm is None else self.arm.received


def make_rig(tmp_path: Path, model: Path) -> Rig:
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(small_cell_dict()))
    cell = load_cell(path)
    scene = SyntheticScene(cell, box=None)
    rig = Rig(tmp_path, model, cell, scene)
    rng = np.random.default_rng(0)
    with rig.cameras() as cams:
        bg = capture_background(cams, cell)
        bg.save(tmp_path / "background.npz")
        scene.box = GOAL
        Goal(segment(cams.capture(), bg, cell, rng).obj_points, "captured").save(tmp_path / "goal.npz")
    scene.box = START
    return rig


def push_towards_robot(dep: Deployment, motion=(-1.0, 0.0, 0.0)):
    """Replace the untrained policy's choice by a known-good one: the point on the object's far
    (+x) face, pushing ``motion`` (default towards the robot). ``motion`` may be a list per step."""
    calls = {"n": 0}
    motions = motion if isinstance(motion, list) else None

    def act(points, features, rng, normals=None, feasible=None):  # scripted: ignores normals, feasibility
        n_obj = dep.policy.n_obj
        obj = points[:n_obj]
        z_ok = obj[:, 2] > dep.cell.floor_z + 0.015
        score = np.where(z_ok, obj[:, 0], -np.inf)
        index = int(np.argmax(score))
        m = motions[min(calls["n"], len(motions) - 1)] if motions is not None else motion
        calls["n"] += 1
        return index, np.asarray(m, dtype=np.float32), {}

    dep.policy.act = act
    return calls
