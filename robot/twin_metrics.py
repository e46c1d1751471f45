"""What only the twin can measure: the deploy loop's observations against the simulator's truth.

A real arm knows the object's pose only through registration; the twin (``robot.twin.TwinWorld``)
also knows the true one. Per step: :func:`mask_iou_vs_truth` (the background-subtraction masks vs
MuJoCo's segmentation, pooled over the cameras) and :func:`registration_error` (ADD-S of the
estimated current-to-goal transform vs the true one); per step and episode: :func:`true_distance`
(training's mean goal flow, from the true poses: the twin's true success); per step
:func:`registration_add` (ADD, which tells symmetric poses apart).
"""

from __future__ import annotations

import numpy as np

from robot.registration import adds_error
from sim.contract import symmetric_goal, transform_points
from sim.depth import mask_iou
from sim.symmetry import symmetries


def mask_iou_vs_truth(world, masks: list[np.ndarray]) -> float:
    """IoU of the object masks (one (H, W) bool per cell camera, in order) vs the twin's true masks."""
    true = np.stack([world.true_mask(i) for i in range(len(masks))])
    return mask_iou(np.stack(masks), true)


def nearest_true_goal(world, T_goal: np.ndarray) -> np.ndarray:
    """Of the poses that look exactly like the true goal ``T_goal`` (the object's symmetries), the one
    nearest the object's true pose: the training env's goal (``sim.contract.symmetric_goal``)."""
    asset = world.asset
    return symmetric_goal(world.object_T(), T_goal, asset.surface_points, symmetries(asset))


def true_distance(world, T_goal: np.ndarray) -> float:
    """Mean goal flow (m) of the object's surface samples from its true pose to the true goal ``T_goal``
    (up to the object's symmetry, as in training)."""
    T_obj = world.object_T()
    surf = transform_points(T_obj, world.asset.surface_points)
    flow = transform_points(nearest_true_goal(world, T_goal) @ np.linalg.inv(T_obj), surf) - surf
    return float(np.linalg.norm(flow, axis=1).mean())


def registration_add(world, T_estimated: np.ndarray, T_goal: np.ndarray) -> float:
    """ADD (m): mean ``‖T_est·p − T_true·p‖`` over the object's surface samples at its true pose.

    Unlike ADD-S it tells symmetric poses apart: ADD-S ≈ 0 with a large ADD is a registration that
    picked a symmetric twin of the goal (a flow towards the wrong one of equal-looking poses)."""
    T_obj = world.object_T()
    T_true = nearest_true_goal(world, T_goal) @ np.linalg.inv(T_obj)
    surf = transform_points(T_obj, world.asset.surface_points)
    diff = transform_points(T_estimated, surf) - transform_points(T_true, surf)
    return float(np.linalg.norm(diff, axis=1).mean())


def registration_error(world, T_estimated: np.ndarray, T_goal: np.ndarray) -> float:
    """ADD-S (m) of the registration's current-to-goal transform vs the true one (true goal ``T_goal``)."""
    T_obj = world.object_T()
    T_true = T_goal @ np.linalg.inv(T_obj)
    surf = transform_points(T_obj, world.asset.surface_points)
    return adds_error(T_estimated, T_true, surf)
