from __future__ import annotations

import numpy as np

from zoffload.sources.sim import VLP16, cast_scan, warehouse, warehouse_loop
from zoffload.sources.sim.scene import Scene
from zoffload.sources.simulated import SimulatedSource


def small_scene() -> Scene:
    return Scene(
        box_min=np.array([[5.0, -50, 0], [-3, 2.0, 0.0]]),
        box_max=np.array([[6.0, 50, 10], [-2, 3.0, 1.0]]),
        cylinders=np.array([[0.0, -4.0, 0.5, 0.0, 2.0]]),
    )


def test_every_point_lies_on_the_surface_it_hit() -> None:
    pose = np.eye(4)
    pose[:3, 3] = [0.3, 0.1, 0.8]
    w = cast_scan(small_scene(), pose, VLP16, None).astype(np.float64) + pose[:3, 3]
    floor = np.abs(w[:, 2]) < 1e-5
    wall = np.abs(w[:, 0] - 5.0) < 1e-5
    box = (w[:, 0] > -3 - 1e-5) & (w[:, 0] < -2 + 1e-5) & (w[:, 1] > 2 - 1e-5) & (w[:, 1] < 3 + 1e-5)
    cyl = np.abs(np.hypot(w[:, 0], w[:, 1] + 4) - 0.5) < 1e-4
    assert floor.sum() > 1000 and wall.sum() > 1000 and box.sum() > 100 and cyl.sum() > 100
    assert (floor | wall | box | cyl).all()
    assert w[wall, 2].max() <= 10 + 1e-4 and w[box, 2].max() <= 1 + 1e-4


def test_beam_pattern_is_vlp16_like() -> None:
    assert VLP16.columns == 1800 and len(VLP16.elevations_deg) == 16 and VLP16.rays == 28800
    pose = np.eye(4)
    pose[2, 3] = 0.8
    pts = cast_scan(small_scene(), pose, VLP16, None)
    el = np.degrees(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1])))
    assert np.allclose(np.unique(np.round(el, 3)), np.arange(-15, 16, 2), atol=1e-3)


def test_trajectory_starts_at_rest_and_reaches_speed() -> None:
    tr = warehouse_loop(speed=1.2)
    p0, p1 = tr.pose_at(0.0)[:3, 3], tr.pose_at(0.1)[:3, 3]
    assert np.linalg.norm(p1[:2] - p0[:2]) < 0.01
    a, b = tr.pose_at(10.0)[:3, 3], tr.pose_at(10.1)[:3, 3]
    assert abs(np.linalg.norm(b[:2] - a[:2]) - 0.12) < 0.01


def test_scene_leaves_the_path_clear() -> None:
    tr = warehouse_loop()
    scene = warehouse(tr.xy, seed=0)
    labels = np.array(scene.labels)
    # No box footprint within 0.5 m of the path (walls excepted: the path keeps 2 m from them)
    for lo, hi, lab in zip(scene.box_min, scene.box_max, labels, strict=True):
        dx = np.maximum(0, np.maximum(lo[0] - tr.xy[:, 0], tr.xy[:, 0] - hi[0]))
        dy = np.maximum(0, np.maximum(lo[1] - tr.xy[:, 1], tr.xy[:, 1] - hi[1]))
        assert np.hypot(dx, dy).min() > 0.5, lab
    for c in scene.cylinders:
        assert np.hypot(tr.xy[:, 0] - c[0], tr.xy[:, 1] - c[1]).min() > 1.0


def test_simulated_source_is_deterministic_and_has_ground_truth() -> None:
    src = SimulatedSource(seed=3)
    a, b = src.read(12), src.read(12)
    np.testing.assert_array_equal(a.points, b.points)
    assert a.gt_pose is not None and a.gt_pose.shape == (4, 4)
    assert 20_000 < len(a.points) <= 28_800
    assert len(src) > 1000  # one lap at 1.2 m/s and 10 Hz
