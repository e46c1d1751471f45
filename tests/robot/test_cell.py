"""The cell file: the shipped example loads, matches the training cameras, and bad cells are refused."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml

from robot.cell import EXAMPLE_CELL, MAX_PUSH_SEGMENT_M, load_cell, parse_cell
from robot.errors import CellError


def example() -> dict:
    return yaml.safe_load(EXAMPLE_CELL.read_text())


def test_example_cell_loads_and_is_consistent(cell):
    assert cell.robot_type == "panda" and len(cell.cameras) == 3
    lim = cell.limits
    assert lim.cartesian_stiffness * MAX_PUSH_SEGMENT_M <= lim.force_stop < lim.collision_force - 5
    assert lim.push_speed <= 0.05 and lim.transit_speed <= 0.10
    assert cell.workspace.floor_z == pytest.approx(cell.bin_center[2])


def test_example_cell_bin_and_workspace_are_the_training_scenes(cell):
    """The policy trains with the training scene's bin and workspace box (feasibility mask, refused
    plans); the shipped cell must be that bin and box, moved to where the arm reaches all of it."""
    from sim.primitive import BIN_INNER_SIZE_M, SIM_WORKSPACE

    np.testing.assert_allclose(cell.bin_size, BIN_INNER_SIZE_M, atol=1e-9)
    shift = cell.bin_center  # the training bin frame: floor top at z = 0, centred at x = y = 0
    np.testing.assert_allclose(np.array(cell.workspace.low) - shift, SIM_WORKSPACE.low, atol=1e-9)
    np.testing.assert_allclose(np.array(cell.workspace.high) - shift, SIM_WORKSPACE.high, atol=1e-9)


def test_example_cameras_are_the_training_scene_cameras_shifted_by_the_bin(cell):
    """The twin's cell must see the bin like the training renderer (sim/assets/scene.xml) does."""
    import mujoco

    from sim.depth import pinhole_intrinsics
    from sim.render import camera_pose_cv
    from sim.scene import ASSETS

    m = mujoco.MjModel.from_xml_path(str(ASSETS / "scene.xml"))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    for spec, name in zip(cell.cameras, ("cam_front", "cam_left", "cam_right"), strict=True):
        cid = m.camera(name).id
        T = camera_pose_cv(d, cid)
        T[:3, 3] += cell.bin_center
        np.testing.assert_allclose(spec.T_base_camera, T, atol=2e-6)
        np.testing.assert_allclose(
            spec.K, pinhole_intrinsics(m.cam_fovy[cid], spec.width, spec.height), atol=1e-5
        )


def test_refuses_a_cell_without_fingertip_offset(tmp_path):
    data = example()
    del data["tool"]["fingertip_offset_m"]
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(CellError, match="fingertip_offset_m.*missing.*never\\s+assumes"):
        load_cell(path)


@pytest.mark.parametrize(
    "limits, match",
    [
        ({"cartesian_stiffness_npm": 800}, "800 x longest push segment"),  # 41.6 N > 30 N stop
        ({"force_stop_n": 36}, "must be below collision_force_n"),  # 36 >= 40 - 5
        ({"push_speed_mps": 0.2}, "push_speed_mps.*<= 0.05"),
    ],
)
def test_refuses_inconsistent_force_and_speed_settings(limits, match):
    data = example()
    data["limits"].update(limits)
    with pytest.raises(CellError, match=match):
        parse_cell(data, "cell.yaml")


def test_refuses_bad_values_naming_the_key():
    cases = [
        (("workspace", "high_m"), [0.9, 0.258, 0.27], "inside the bin"),
        (("cameras", 0, "T_base_camera"), np.eye(4)[[1, 0, 2, 3]].tolist(), "rigid transform"),
        (("robot", "type"), "ur5", "robot.type"),
        (("tool", "fingertip_offset_m"), [0, 0, 112.4], "millimetres"),
        (("limits", "force_stop"), 30, "`limits.force_stop` is not a known key"),
    ]
    for keys, value, match in cases:
        data = copy.deepcopy(example())
        node = data
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value
        with pytest.raises(CellError, match=match):
            parse_cell(data, "cell.yaml")


def test_missing_cell_file_says_how_to_start(tmp_path):
    with pytest.raises(CellError, match="cp .*cell.example.yaml"):
        load_cell(tmp_path / "nope.yaml")
