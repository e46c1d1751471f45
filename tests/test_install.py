"""One install command: the Panda model ships inside the package (no second pip line), the optional
extras are pinned, and ``python -m sim.goals`` on user meshes shows its progress."""

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import mujoco

from sim.scene import PANDA_ASSETS

ROOT = Path(__file__).resolve().parents[1]


def test_the_panda_model_ships_with_its_licence_and_stays_small():
    names = {p.name for p in PANDA_ASSETS.iterdir()}
    meshes = {f"link{i}.stl" for i in range(8)} | {"hand.stl", "finger.stl"}
    assert {"panda.xml", "LICENSE", "NOTICE"} | meshes <= names
    assert "dm-robotics-panda 0.4.8" in (PANDA_ASSETS / "NOTICE").read_text()
    assert "Apache License" in (PANDA_ASSETS / "LICENSE").read_text()
    size = sum(p.stat().st_size for p in PANDA_ASSETS.iterdir())
    assert size < 5e6, f"sim/assets/panda is {size / 1e6:.1f} MB"
    model = mujoco.MjModel.from_xml_path(str(PANDA_ASSETS / "panda.xml"))
    assert model.njnt == 7 and model.nmesh == 8


def test_no_code_looks_for_the_dm_robotics_package():
    offenders = [
        str(p.relative_to(ROOT))
        for pkg in ("sim", "robot", "hydo_cli")
        for p in (ROOT / pkg).rglob("*.py")
        if re.search(r"distribution\(\"dm-robotics|import dm_robotics|from dm_robotics", p.read_text())
    ]
    assert offenders == []


def test_extras_are_pinned_and_the_tests_cover_them():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    extras = project["project"]["optional-dependencies"]
    assert extras["plot"] == ["matplotlib==3.11.2"]
    assert extras["cluster"] == ["ray[tune]==2.60.0"]
    assert set(extras["plot"] + extras["cluster"]) <= set(extras["test"])
    package_data = project["tool"]["setuptools"]["package-data"]["sim"]
    assert "assets/**/*" in package_data
    ci = (ROOT / ".ci" / "run").read_text()
    readme = (ROOT / "README.md").read_text()
    assert "install --no-deps dm-robotics" not in ci and "install --no-deps dm-robotics" not in readme


def test_sim_goals_on_user_meshes_shows_progress(tmp_path):
    import trimesh

    meshes = tmp_path / "meshes"
    meshes.mkdir()
    trimesh.creation.box((0.05, 0.08, 0.03)).export(meshes / "crate.stl")
    trimesh.creation.cylinder(0.03, 0.1).export(meshes / "can.obj")
    env = {**os.environ, "HYDO_CACHE": str(tmp_path / "cache"), "COLUMNS": "120"}
    r = subprocess.run(
        [sys.executable, "-m", "sim.goals", str(meshes)], capture_output=True, text=True, env=env, timeout=600
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "crate" in r.stdout and "can" in r.stdout and "2/2" in r.stdout  # a bar per object, one overall
    assert len(list((tmp_path / "cache" / "stable_poses").glob("*.npz"))) == 2
    r = subprocess.run(
        [sys.executable, "-m", "sim.goals", str(tmp_path / "nothing")],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 1 and "Traceback" not in r.stderr and "unknown object spec" in r.stderr
