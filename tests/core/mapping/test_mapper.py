"""The KISS-ICP mapper on simulated scans."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.lab.eval.trajectory import trajectory_error
from zoffload.mapping.mapper import RobotMapper, mapper_voxel_size
from zoffload.mapping.voxel import voxel_downsample
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")


def test_mapper_voxel_follows_sensor_and_robot_voxels() -> None:
    assert mapper_voxel_size(100.0, 0.07) == 1.0  # KISS-ICP's own default
    assert mapper_voxel_size(40.0, 0.07) == 0.4
    assert mapper_voxel_size(20.0, 0.3) == 0.6  # never finer than twice the robot's voxel
    assert mapper_voxel_size(20.0, 0.3, configured=0.25) == 0.25


def test_kiss_icp_tracks_the_simulated_warehouse() -> None:
    src = SimulatedSource()
    m = RobotMapper(voxel_size=0.4, max_range=src.max_range)
    gt = []
    counts = []
    for i in range(60):
        f = src.read(i)
        r = m.register(i, voxel_downsample(f.points, 0.05))
        gt.append(f.gt_pose)
        counts.append(r.map_points)
        assert r.keypoints > 100 and np.isfinite(r.sigma)
    seqs, poses = m.trajectory()
    err = trajectory_error(seqs, poses, np.arange(60), np.array(gt))
    assert err is not None and err.path_length > 4.0
    assert err.ate_rmse < 0.3, err
    assert counts[-1] > counts[0] and all(b >= a for a, b in zip(counts, counts[1:], strict=False))
    assert len(m.map_cloud()) == m.map_points


def test_lost_scans_do_not_derail_the_mapper() -> None:
    """Every 20 scans, 10 are lost (1 s of a 1.2 m/s robot): the seq gap stretches the motion model."""
    src = SimulatedSource()
    kept = [i for i in range(140) if i < 30 or (i % 20) < 10]
    m = RobotMapper(voxel_size=0.4, max_range=src.max_range)
    gt = {}
    motions = []
    for i in kept:
        f = src.read(i)
        r = m.register(i, voxel_downsample(f.points, 0.05))
        gt[i] = f.gt_pose
        motions.append(r.gap_motion)
    seqs, poses = m.trajectory()
    err = trajectory_error(seqs, poses, np.array(kept), np.array([gt[i] for i in kept]))
    assert err is not None and err.ate_rmse < 0.5, err
    # the robot kept its motion over every gap: no other guess replaced the constant-velocity one
    assert motions.count("kept") == 5 and set(motions) == {"", "kept"}, motions


def test_map_overlap_is_the_share_of_points_in_mapped_cells() -> None:
    from zoffload.mapping.mapper import _cell_keys, map_overlap

    cloud = np.array([[0.1, 0.1, 0.1], [1.1, 0.1, 0.1], [2.1, 0.1, 0.1], [-0.9, 0.2, 0.3]])
    keys = np.unique(_cell_keys(cloud, 0.5))
    pose = np.eye(4)
    assert map_overlap(cloud, pose, keys, 0.5) == 1.0
    pose[0, 3] = 1.0  # one step along x: the point moved past 2.1 m falls in an empty cell
    assert map_overlap(cloud, pose, keys, 0.5) == 0.75
    pose[0, 3] = 10.0
    assert map_overlap(cloud, pose, keys, 0.5) == 0.0
    assert map_overlap(cloud[:0], np.eye(4), keys, 0.5) == 0.0
    assert map_overlap(cloud, np.eye(4), keys[:0], 0.5) == 0.0


def test_a_scan_lost_as_the_robot_reverses_does_not_shift_the_map(kitti_dir) -> None:
    """KITTI-360 (the car ~1.3 m a scan) driven forth and back: the scan right after the
    turnaround is lost, so the constant-velocity guess for the next one is four scans (~4 m) off
    along the street; from there KISS-ICP alone settles ~3.8 m off (half the scan still fits a
    street) and the whole map after it with it. Registered from the stopped and reversed guesses
    too, the one that fits the map is kept."""
    files = sorted(kitti_dir.glob("*.bin"))[20:50]
    scans = [voxel_downsample(np.fromfile(f, np.float32).reshape(-1, 4)[:, :3].copy(), 0.278) for f in files]
    order = list(range(30)) + [28, 27, 26, 25, 24]  # forth, then back from the turnaround at 29

    def run(lost: set[int]) -> tuple[dict[int, np.ndarray], dict[int, str]]:
        m = RobotMapper(voxel_size=1.0, max_range=100.0)
        poses, motions = {}, {}
        for step, idx in enumerate(order):
            if step not in lost:
                r = m.register(step, scans[idx])
                poses[step], motions[step] = r.pose, r.gap_motion
        return poses, motions

    ref, _ = run(set())
    got, motions = run({30})
    assert motions[31] in ("stopped", "reversed"), motions
    for step in (31, 34):
        moved = np.linalg.inv(got[29]) @ got[step]
        truth = np.linalg.inv(ref[29]) @ ref[step]
        assert np.linalg.norm(moved[:3, 3] - truth[:3, 3]) < 0.3, step


def test_deskew_times_are_kiss_icp_safe() -> None:
    from zoffload.mapping.mapper import deskew_times

    np.testing.assert_allclose(deskew_times(np.array([5.0, 5.05, 5.1]), 3), [0.0, 0.5, 1.0])
    # KISS-ICP 1.3 aborts the process on all-equal times: none is no deskew instead
    assert deskew_times(np.zeros(3), 3).size == 0 and deskew_times(None, 3).size == 0
    with pytest.raises(ValueError, match="2 point times for 3 points"):
        deskew_times(np.zeros(2), 3)
    with pytest.raises(ValueError, match="non-finite"):
        deskew_times(np.array([0.0, np.nan, 1.0]), 3)
    m = RobotMapper(voxel_size=0.4, max_range=40.0, deskew=True)
    f = SimulatedSource().read(0)
    m.register(0, f.points, np.full(len(f.points), 7.0))  # equal times: registered, not aborted
    m.register(1, f.points, None)
    assert len(m.trajectory()[0]) == 2


def test_deskew_undoes_the_sweep_of_a_fast_turning_robot() -> None:
    """4 m/s through the warehouse's corners, each column fired at its own time (sim ``sweep``):
    without deskew the skewed scans cost accuracy, with the points' times it comes back to the
    level of scans cast without motion (benchmarks/bench_deskew.py measures it at length)."""
    swept, still = SimulatedSource(speed=4.0, sweep=True), SimulatedSource(speed=4.0)
    n = 50
    frames = [swept.read(i) for i in range(n)]
    gt = np.array([f.gt_pose for f in frames])
    ate = {}
    for name, deskew, source in (("skewed", False, frames), ("deskewed", True, frames),
                                 ("still", False, [still.read(i) for i in range(n)])):
        m = RobotMapper(voxel_size=0.4, max_range=swept.max_range, deskew=deskew)
        for i, f in enumerate(source):
            m.register(i, f.points, f.times)
        seqs, poses = m.trajectory()
        err = trajectory_error(seqs, poses, np.arange(n), gt)
        assert err is not None
        ate[name] = err.ate_rmse
    assert ate["deskewed"] < 0.85 * ate["skewed"], ate
    assert ate["deskewed"] < 1.2 * ate["still"] + 0.02, ate


def test_kiss_icp_gets_row_major_points_whatever_the_layout_it_is_handed(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """KISS-ICP's binding converts a column-major array point by point (hundreds of times slower than a
    row-major one): the edge's mapper and the robot's local odometry hand it row-major points
    whatever they were given, and register them as the row-major copy (to the last bits of
    KISS-ICP's multithreaded sums)."""
    from kiss_icp import preprocess

    from zoffload.robot.odometry import LocalOdometry

    convert = preprocess.kiss_icp_pybind._Vector3dVector
    layouts: list[bool] = []

    def recorded(points: np.ndarray) -> object:
        layouts.append(bool(points.flags["C_CONTIGUOUS"]))
        return convert(points)

    monkeypatch.setattr(preprocess.kiss_icp_pybind, "_Vector3dVector", recorded)
    src = SimulatedSource()
    scans = [voxel_downsample(src.read(i).points, 0.05) for i in range(4)]
    runs = []
    for layout in (np.asfortranarray, np.ascontiguousarray):
        m = RobotMapper(voxel_size=0.4, max_range=src.max_range)
        odo = LocalOdometry("robot1", src.max_range, threads=1)
        odo.begin(None, [])
        poses = []
        for i, s in enumerate(scans):
            poses.append(m.register(i, layout(s)).pose)
            poses.append(odo.register(i, layout(s), float(i))[0])
        runs.append(np.array(poses))
    assert len(layouts) >= 16 and all(layouts)
    np.testing.assert_allclose(runs[0], runs[1], rtol=0, atol=1e-9)
