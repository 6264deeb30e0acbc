"""A mapper continuing a robot's trajectory: seeded from a checkpoint, with the robot's own poses
in its trajectory, and, for a robot coming back to a mapper it had, re-seeded only by a newer
checkpoint while its global map stays."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from zoffload.edge.recipe import MapperRecipe
from zoffload.mapping.checkpoint import config_matches, take_checkpoint
from zoffload.mapping.mapper import RobotMapper, _yaw, motion_per_scan
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")
SRC = SimulatedSource()
SCANS = [voxel_downsample(SRC.read(i).points, 0.05) for i in range(40)]


def mapper() -> RobotMapper:
    return RobotMapper(voxel_size=0.5, max_range=SRC.max_range)


def test_a_fresh_mapper_continues_the_checkpoint_and_the_robots_own_poses() -> None:
    a = mapper()
    regs = [a.register(i, SCANS[i]) for i in range(30)]
    cp = take_checkpoint(a.odometry, "r1", "e1", epoch=1, seq=29, stamp=0.0)
    b = mapper()
    # The robot registered 30..32 itself (here: the original mapper's poses stand in for them)
    local = [a.register(i, SCANS[i]).pose for i in range(30, 33)]
    assert b.continue_from(cp, np.arange(30, 33), np.asarray(local))
    assert b.seqs == [30, 31, 32] and b.last_seq == 32 and b.registered == 0
    np.testing.assert_allclose(b.odometry.last_pose, local[-1])
    for i in range(33, 40):
        ra, rb = a.register(i, SCANS[i]), b.register(i, SCANS[i])
    assert np.linalg.norm(ra.pose[:3, 3] - rb.pose[:3, 3]) < 0.05  # same frame, same place
    assert np.linalg.norm(rb.pose[:3, 3]) > 2.0 and regs[-1].pose[0, 3] != 0  # not back at the origin
    seqs, poses = b.trajectory()
    assert seqs.tolist() == list(range(30, 40)) and b.registered == 7


def test_a_mapper_with_history_is_reseeded_only_by_a_newer_checkpoint() -> None:
    a = mapper()
    for i in range(20):
        a.register(i, SCANS[i])
    old = take_checkpoint(a.odometry, "r1", "e1", epoch=1, seq=10, stamp=0.0)
    pose = a.odometry.last_pose.copy()
    points = a.map_points
    assert not a.continue_from(old, np.zeros(0, np.int64), np.zeros((0, 4, 4)))  # older: ignored
    np.testing.assert_allclose(a.odometry.last_pose, pose)
    # Elsewhere the robot went on to scan 30; it comes back with that checkpoint
    other = mapper()
    for i in range(31):
        other.register(i, SCANS[i])
    newer = take_checkpoint(other.odometry, "r1", "e2", epoch=2, seq=30, stamp=0.0)
    assert a.continue_from(newer, np.zeros(0, np.int64), np.zeros((0, 4, 4)))
    assert a.last_seq == 30 and a.map_points == points and len(a.seqs) == 20  # global map, trajectory kept
    for i in range(31, 36):
        ra, ro = a.register(i, SCANS[i]), other.register(i, SCANS[i])
    assert np.linalg.norm(ra.pose[:3, 3] - ro.pose[:3, 3]) < 0.05


def test_the_bounded_mapper_checkpoints_after_its_last_scan() -> None:
    scan = wire.Scan(robot="r1", seq=0, send_stamp=0.0, capture_stamp=0.0, voxel=0.05, voxel_max=0.07,
                     max_range=SRC.max_range, n_raw=0, points=np.zeros((0, 3), np.float32))
    m = MapperRecipe()(scan)
    assert m.checkpoint("r1", "e1", 3, 5.0) is None  # nothing registered yet
    for i in range(5):
        m.register(i, SCANS[i])
    cp = m.checkpoint("r1", "e1", 3, 5.0, resolution=1.0, final=True)
    assert cp is not None and cp.seq == 4 and cp.final and cp.epoch == 3 and cp.edge == "e1"
    np.testing.assert_allclose(cp.pose, m.inner.poses[-1])
    assert m.scans == 5


def test_the_robots_coarse_checkpoint_does_not_replace_a_finer_local_map() -> None:
    """Back on the edge that mapped it, with a checkpoint of its own local odometry (another voxel
    size): the edge keeps its own local map and continues from the robot's pose."""
    a = mapper()
    for i in range(25):
        a.register(i, SCANS[i])
    local_map = len(np.asarray(a.odometry.local_map.point_cloud()))
    robot = RobotMapper(voxel_size=1.0, max_range=SRC.max_range)  # the robot's coarse odometry
    for i in range(29):
        robot.register(i, SCANS[i])
    own = take_checkpoint(robot.odometry, "r1", "", epoch=0, seq=28, stamp=0.0)
    assert not a.continue_from(own, np.zeros(0, np.int64), np.zeros((0, 4, 4)))  # not seeded
    assert len(np.asarray(a.odometry.local_map.point_cloud())) == local_map and a.last_seq == 28
    np.testing.assert_allclose(a.odometry.last_pose, own.pose)
    for i in range(29, 34):
        r = a.register(i, SCANS[i])
    ref = mapper()
    for i in range(34):
        rr = ref.register(i, SCANS[i])
    assert np.linalg.norm(r.pose[:3, 3] - rr.pose[:3, 3]) < 0.1


def test_the_robots_checkpoint_at_the_edges_own_voxel_does_not_replace_its_local_map() -> None:
    """The robot's local odometry configured as the edge's mapper (``fleet.local_voxel`` at the
    edge's voxel) made a checkpoint the edge's configuration matched, and the edge replaced its own
    local map with the robot's, drifted over the outage (cellular-heldout: trajectory +68 % of
    local's over the same scans). A checkpoint of the robot's own (edge "") is never seeded from by
    a mapper that has mapped the robot; an edge's checkpoint still is."""
    a = mapper()
    for i in range(25):
        a.register(i, SCANS[i])
    local_map = np.asarray(a.odometry.local_map.point_cloud()).copy()
    robot = mapper()  # the robot's odometry, configured as the edge's
    for i in range(29):
        robot.register(i, SCANS[i])
    own = take_checkpoint(robot.odometry, "r1", "", epoch=0, seq=28, stamp=0.0)
    assert config_matches(a.odometry, own)
    assert not a.continue_from(own, np.zeros(0, np.int64), np.zeros((0, 4, 4)))  # not seeded
    np.testing.assert_array_equal(np.asarray(a.odometry.local_map.point_cloud()), local_map)
    np.testing.assert_allclose(a.odometry.last_pose, own.pose)
    other = dataclasses.replace(take_checkpoint(robot.odometry, "r1", "e2", 3, 28, 0.0), seq=30)
    assert a.continue_from(other, np.zeros(0, np.int64), np.zeros((0, 4, 4)))  # another edge's: seeded


def test_a_mapper_continues_the_robots_motion_not_the_one_it_saw_before() -> None:
    """The robot turned back while away (pingpong over the recorded scans): the edge's last motion
    points the wrong way, and stretched over the gap before its next scan it put that scan
    metres off (KITTI-360, held-out cellular link: 5 and 10 m of trajectory error)."""
    path = list(range(40)) + list(range(38, 0, -1))  # seq -> recorded scan: forward, then back
    ref = mapper()
    ref_poses = [ref.register(s, SCANS[i]).pose for s, i in enumerate(path[:60])]
    edge = mapper()
    for s in range(36):
        edge.register(s, SCANS[path[s]])
    # Away from seq 36 to 45; the robot's own poses (the reference's stand in) go back the other way
    edge.continue_from(None, np.arange(36, 46), np.asarray(ref_poses[36:46]))
    robot_step = (np.linalg.inv(ref_poses[44]) @ ref_poses[45])[:3, 3]
    assert edge.odometry.last_delta[:3, 3] @ robot_step > 0  # the same direction
    for s in range(54, 58):  # the next scan after a gap of 9
        r = edge.register(s, SCANS[path[s]])
        assert np.linalg.norm(r.pose[:3, 3] - ref_poses[s][:3, 3]) < 0.1


def test_the_motion_per_scan_is_averaged_over_the_newest_poses() -> None:
    def at(x: float) -> np.ndarray:
        p = np.eye(4)
        p[0, 3] = x
        return p

    seqs = np.array([10, 11, 13, 14])
    poses = np.array([at(0.0), at(1.0), at(3.2), at(3.9)])  # noisy steps around 1 m per scan
    d = motion_per_scan(seqs, poses)
    assert d is not None and d[0, 3] == pytest.approx((3.9 - 1.0) / 3)  # from 11 to 14
    assert motion_per_scan(seqs[:1], poses[:1]) is None  # nothing to compare with
    d = motion_per_scan(seqs[:1], poses[:1], anchor=(8, at(-2.0)))  # from the pose before the hand-over
    assert d is not None and d[0, 3] == pytest.approx(1.0)
    assert motion_per_scan(np.array([100]), poses[:1], anchor=(8, at(-2.0)), max_gap=50) is None


def test_a_scan_after_an_outage_in_a_turn_is_predicted_from_the_robots_own_estimate() -> None:
    """The simulator's robot turns ~120 degrees over scans 786-804. An edge that missed those scans
    stretches its constant-velocity model over the gap and converges metres off; predicted from
    the robot's own (coarse) odometry, which registered every scan, it stays on the trajectory.
    A following scan, or an estimate no newer than the mapper's last scan, changes nothing."""
    start, last_seen, back = 776, 786, 804
    raw = {i: SRC.read(i) for i in range(start, back + 3)}

    def error(pose: np.ndarray, i: int) -> float:  # both frames start at scan ``start``
        truth = np.linalg.inv(raw[start].gt_pose) @ raw[i].gt_pose
        return float(np.linalg.norm(pose[:3, 3] - truth[:3, 3]))

    local = RobotMapper(voxel_size=0.8, max_range=SRC.max_range)  # the robot's coarse odometry
    for i in range(start, back + 1):
        local.register(i, raw[i].points)
    edges = []
    for use_prior in (False, True):
        m = RobotMapper(voxel_size=0.4, max_range=SRC.max_range)
        for i in range(start, last_seen + 1):
            m.register(i, voxel_downsample(raw[i].points, 0.1))
        pose_before = m.odometry.last_pose.copy()
        assert not m.predict_from(back, last_seen, local.poses[last_seen - start], np.eye(4))  # not newer
        assert not m.predict_from(back, back - m.max_gap, local.poses[-1], np.eye(4))  # too old
        np.testing.assert_array_equal(m.odometry.last_pose, pose_before)
        if use_prior:  # (contested by the mapper's own guess, as the edge does a scan's prior)
            assert m.predict_from(back, back, local.poses[-1], local.odometry.last_delta, contest=True)
        errors = [error(m.register(i, voxel_downsample(raw[i].points, 0.1)).pose, i)
                  for i in range(back, back + 3)]
        assert not m.predict_from(back + 3, back + 2, local.poses[-1], np.eye(4))  # no gap: ignored
        edges.append(errors)
    stretched, predicted = edges
    assert min(stretched) > 0.5, stretched  # the constant-velocity guess lost the robot
    assert max(predicted) < 0.25, predicted
    assert m.seqs[-3:] == [back, back + 1, back + 2]  # the trajectory holds the registered scans


@pytest.mark.parametrize(("yaw", "shift", "winner"), [(15.0, (2.0, 2.2), "prior"), (40.0, (4.0, 3.0), "own")])
def test_a_robots_estimate_metres_off_costs_the_mapper_nothing(yaw: float, shift: tuple[float, float],
                                                               winner: str) -> None:
    """A scan's prior is the robot's own odometry, which can go wrong (a gap in a turn): here 3 m
    and 15 degrees off on a straight stretch, and 5 m and 40 degrees. Contested (``contest``, what
    the edge does with a scan's prior) the mapper keeps the scans after it on the trajectory:
    from 3 m off ICP finds the scan's pose, and the motion on is the robot's per scan, not the
    correction of its pose; from 5 m off ICP cannot, and the mapper's own guess wins. Taken as
    before, the first left the motion model metres a scan (2.9, 6.0, 9.0 m off in the next three
    scans), the second converged 5 m off and stayed there."""
    start, last_seen, back = 40, 60, 64
    raw = {i: SRC.read(i) for i in range(start, back + 4)}

    def error(pose: np.ndarray, i: int) -> float:  # both frames start at scan ``start``
        truth = np.linalg.inv(raw[start].gt_pose) @ raw[i].gt_pose
        return float(np.linalg.norm(pose[:3, 3] - truth[:3, 3]))

    wrong = np.linalg.inv(raw[start].gt_pose) @ raw[back].gt_pose @ _yaw(np.radians(yaw))
    wrong[:2, 3] += shift
    runs = []
    for contest in (True, False):
        m = RobotMapper(voxel_size=0.4, max_range=SRC.max_range)
        for i in range(start, last_seen + 1):
            m.register(i, voxel_downsample(raw[i].points, 0.1))
        assert m.predict_from(back, back, wrong, np.eye(4), contest=contest)
        regs = [m.register(i, voxel_downsample(raw[i].points, 0.1)) for i in range(back, back + 4)]
        runs.append([error(r.pose, i) for r, i in zip(regs, range(back, back + 4), strict=True)])
        if contest:
            assert regs[0].gap_motion == winner
    contested, taken = runs
    assert max(contested) < 0.25, contested
    assert max(taken) > 2.0, taken


def test_a_robots_estimate_of_an_impossible_motion_is_not_taken() -> None:
    """A scan's prior comes from the network: a motion per scan no robot has (100 m, or a turn of
    90 degrees a period) is refused, and the mapper's state is left as it was."""
    m = RobotMapper(voxel_size=0.4, max_range=SRC.max_range)
    for i in range(40, 50):
        m.register(i, voxel_downsample(SRC.read(i).points, 0.1))
    before = (m.odometry.last_pose.copy(), m.odometry.last_delta.copy(), m.last_seq)
    far, turned = np.eye(4), _yaw(np.radians(90.0))
    far[0, 3] = 100.0
    for delta in (far, turned):
        assert not m.predict_from(54, 54, m.odometry.last_pose, delta, contest=True)
    np.testing.assert_array_equal(m.odometry.last_pose, before[0])
    assert m.last_seq == before[2] and m._prior is None
    assert m.predict_from(54, 54, m.odometry.last_pose, np.eye(4), contest=True)  # a stop: taken


def test_a_mapper_registers_the_robots_backfill_instead_of_jumping_the_outage() -> None:
    """The robot mapped a 45-scan outage itself (coarse local odometry) and hands the scans over
    at its odometry's grid with the attach (``backfill``, codec version 9). The edge that mapped it
    registers them in order from its own state, so its trajectory holds its own poses for the
    outage, the scan after it comes with no gap, and the trajectory after the outage stays closer
    to the one the edge would have had with every scan (here 4 cm against 6 cm; two other outages
    of the simulator's drive: 7 against 20 cm, 3 against 5 cm). Jumping the outage to the robot's
    pose, the edge registered that scan against a local map metres behind (cellular-heldout: +30 %
    of local's trajectory error over the same scans, +4 to +9 % backfilled, offline replays)."""
    start, lost, back, end = 40, 100, 145, 175
    raw = {i: SRC.read(i) for i in range(start, end)}
    robot = RobotMapper(voxel_size=0.8, max_range=SRC.max_range)  # the robot's odometry over the outage
    for i in range(start, back):
        robot.register(i, raw[i].points)
    own = take_checkpoint(robot.odometry, "r1", "", epoch=0, seq=back - 1, stamp=0.0)
    seqs, poses = np.arange(lost, back), np.asarray(robot.poses[lost - start:])
    backfill = [(i, voxel_downsample(raw[i].points, 0.8)) for i in range(lost - 2, back)]  # 2 it had
    results = []
    for fill in ([], backfill, None):
        m = RobotMapper(voxel_size=0.4, max_range=SRC.max_range)
        for i in range(start, lost):
            m.register(i, voxel_downsample(raw[i].points, 0.1))
        if fill is None:  # no outage
            for i in range(lost, back):
                m.register(i, voxel_downsample(raw[i].points, 0.1))
        else:
            m.continue_from(own, seqs, poses, fill)
        for i in range(back, end):
            m.register(i, voxel_downsample(raw[i].points, 0.1))
        results.append(m)
    jumped, filled, every = results
    assert jumped.backfilled == 0 and jumped.registered == (lost - start) + (end - back)
    assert filled.backfilled == back - lost and filled.backfill_unused == 2  # the two it had already
    assert filled.registered == end - start  # every scan registered here, none of the robot's poses
    assert filled.seqs == list(range(start, end))
    assert filled.after_gap == 0  # no scan came after a gap

    def off(m: RobotMapper) -> float:  # from the trajectory with every scan, after the outage
        d = [m.poses[m.seqs.index(i)][:3, 3] - every.poses[every.seqs.index(i)][:3, 3]
             for i in range(back, end)]
        return float(np.sqrt(np.mean(np.sum(np.square(d), axis=1))))

    assert off(filled) < 0.8 * off(jumped), (off(filled), off(jumped))


def test_a_fine_backfill_is_registered_at_the_mappers_voxel_and_mapped_whole(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A robot sends its backfill finer where its link has room (0.2 m here, a quarter of its
    odometry's 0.8). The mapper registers each scan from its own voxel's grid (0.4 m:
    ``BACKFILL_REGISTER_GRID``; as sent, the scans held its worker twice as long) and grows its
    global map by all of the scan's points: the outage's map is denser than a 0.4 m backfill's,
    the poses those of the 0.4 m scans."""
    start, lost, back = 40, 100, 130
    raw = {i: SRC.read(i).points for i in range(start, back)}
    robot = RobotMapper(voxel_size=0.8, max_range=SRC.max_range)
    for i in range(start, back):
        robot.register(i, raw[i])
    own = take_checkpoint(robot.odometry, "r1", "", epoch=0, seq=back - 1, stamp=0.0)
    seqs, poses = np.arange(lost, back), np.asarray(robot.poses[lost - start:])

    def run(grid: float) -> tuple[RobotMapper, list[tuple[int, int]], list[np.ndarray], int]:
        m = RobotMapper(voxel_size=0.4, max_range=SRC.max_range)
        for i in range(start, lost):
            m.register(i, voxel_downsample(raw[i], 0.1))
        before = len(m.global_map)
        sizes: list[tuple[int, int]] = []
        register = m.register

        def spy(seq: int, points: np.ndarray, times: np.ndarray | None = None,
                map_points: np.ndarray | None = None) -> object:
            sizes.append((len(points), len(points if map_points is None else map_points)))
            return register(seq, points, times, map_points)

        monkeypatch.setattr(m, "register", spy)
        fill = [voxel_downsample(raw[i], grid) for i in range(lost, back)]
        m.continue_from(own, seqs, poses, list(zip(range(lost, back), fill, strict=True)))
        return m, sizes, fill, len(m.global_map) - before

    fine, fine_sizes, fine_fill, fine_grew = run(0.2)
    coarse, coarse_sizes, _, coarse_grew = run(0.4)
    assert fine.backfilled == coarse.backfilled == back - lost
    assert [r for r, _ in fine_sizes] == [len(voxel_downsample(p, 0.4)) for p in fine_fill]
    assert [g for _, g in fine_sizes] == [len(p) for p in fine_fill]  # mapped whole
    assert fine_grew > 1.3 * coarse_grew, (fine_grew, coarse_grew)
    d = np.linalg.norm(fine.poses[-1][:3, 3] - coarse.poses[-1][:3, 3])
    assert d < 0.1, d  # registered from (nearly) the same 0.4 m scans


def test_a_backfill_the_mapper_cannot_continue_is_left_unused() -> None:
    """A mapper that never mapped the robot (another edge) seeds from the checkpoint and leaves
    the backfill, as it does one whose first newer scan is over ``max_gap`` after its last."""
    fill = [(i, SCANS[i]) for i in range(30, 34)]
    fresh = mapper()
    robot = mapper()
    for i in range(30):
        robot.register(i, SCANS[i])
    cp = take_checkpoint(robot.odometry, "r1", "e1", epoch=1, seq=29, stamp=0.0)
    assert fresh.continue_from(cp, np.zeros(0, np.int64), np.zeros((0, 4, 4)), fill)
    assert fresh.backfilled == 0 and fresh.backfill_unused == 4 and fresh.registered == 0
    far = mapper()
    far.max_gap = 3
    for i in range(26):
        far.register(i, SCANS[i])
    far.continue_from(None, np.zeros(0, np.int64), np.zeros((0, 4, 4)), fill)  # 30 - 25 > 3
    assert far.backfilled == 0 and far.backfill_unused == 4 and far.last_seq == 25
    bounded = MapperRecipe()(wire.decode(wire.encode(wire.Scan(
        robot="r1", seq=0, send_stamp=0.0, capture_stamp=0.0, voxel=0.05, voxel_max=0.07,
        max_range=SRC.max_range, n_raw=len(SCANS[0]), points=SCANS[0].astype(np.float32))), expect=wire.Scan))
    for i in range(26):
        bounded.register(i, SCANS[i])
    beyond = np.full((10, 3), 10 * SRC.max_range)  # no point within the mapper's range: counted, not lost
    bounded.continue_from(None, np.zeros(0, np.int64), np.zeros((0, 4, 4)), [(26, beyond), (27, SCANS[27])])
    assert bounded.backfill_unused == 1 and bounded.backfilled == 1 and bounded.inner.last_seq == 27


def test_a_backfill_after_a_gap_needs_the_robots_pose_and_a_failed_scan_ends_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The backfill's first scan more than ``BACKFILL_GAP`` after the mapper's last: taken only
    with the robot's pose of a scan in that gap to predict it from. A scan KISS-ICP cannot take
    ends the backfill there, the rest left unused. The robot's poses after the backfill join the
    trajectory moved by the correction the mapper found for its last scan."""
    from zoffload.mapping.mapper import BACKFILL_GAP

    robot = mapper()
    for i in range(40):
        robot.register(i, SCANS[i])
    fill = [(i, SCANS[i]) for i in range(26, 34)]
    no_pose = np.zeros(0, np.int64), np.zeros((0, 4, 4))

    def edge() -> RobotMapper:
        m = mapper()
        for i in range(20):
            m.register(i, SCANS[i])
        return m

    assert 26 - 19 > BACKFILL_GAP
    far = edge()
    far.continue_from(None, *no_pose, fill)  # nothing to predict scan 26 from
    assert far.backfilled == 0 and far.backfill_unused == 8 and far.last_seq == 19
    # version 10: the robot's pose of each backfilled scan predicts the first across the gap
    own = edge()
    own.continue_from(None, *no_pose, fill, np.asarray([robot.poses[i] for i in range(26, 34)]))
    assert own.backfilled == 8 and own.seqs[-8:] == list(range(26, 34)) and own.backfill_posed == 1
    assert np.linalg.norm(own.poses[-1][:3, 3] - robot.poses[33][:3, 3]) < 0.1
    # the robot's poses after the backfill (its local ones start after its checkpoint, here 37)
    # join moved by the correction found against its pose of the backfill's last scan
    drifted = edge()
    moved = np.asarray([robot.poses[i] for i in [*range(26, 34), 38, 39]])
    moved[:, 0, 3] += 0.3  # the robot's odometry 30 cm off the edge's frame
    drifted.continue_from(None, np.array([38, 39]), moved[-2:], fill, moved[:-2])
    assert drifted.seqs[-2:] == [38, 39] and drifted.backfilled == 8
    off = np.linalg.norm(drifted.poses[-1][:3, 3] - robot.poses[39][:3, 3])
    assert off < 0.1, off  # the 30 cm taken out
    # a ring thinned over a long outage: gaps between the backfill's scans, each bridged by the
    # robot's own motion from one to the next (its poses 30 cm off this mapper's frame: relative
    # motion only)
    sparse = [20, 21, 25, 29, 33, 37, 38, 39]
    thin = edge()
    shifted = np.asarray([robot.poses[i] for i in sparse])
    shifted[:, 0, 3] += 0.3
    thin.continue_from(None, *no_pose, [(i, SCANS[i]) for i in sparse], shifted)
    assert thin.backfilled == len(sparse) and thin.seqs[-len(sparse):] == sparse and thin.after_gap == 0
    for i in sparse:
        assert np.linalg.norm(thin.poses[thin.seqs.index(i)][:3, 3] - robot.poses[i][:3, 3]) < 0.1, i
    posed = edge()
    seqs = np.array([*range(20, 26), 38, 39])  # the robot's poses: the gap, and two after the backfill
    poses = np.asarray([robot.poses[i] for i in seqs])
    shifted = poses.copy()
    shifted[:, 0, 3] += 0.3  # the robot's odometry 30 cm off the edge's frame
    posed.continue_from(None, seqs, shifted, fill)
    assert posed.backfilled == 8 and posed.seqs[-10:-2] == list(range(26, 34))
    # the robot's own poses after the backfill (38, 39) are in the trajectory, moved by what the
    # mapper found for scan 33 against the robot's pose of it; the robot had none for 33 here, so
    # they join as they came
    np.testing.assert_allclose(posed.poses[-1], shifted[-1])
    corrected = edge()
    seqs2 = np.array([*range(20, 34), 38, 39])
    poses2 = np.asarray([robot.poses[i] for i in seqs2])
    poses2[:, 0, 3] += 0.3
    corrected.continue_from(None, seqs2, poses2, fill)
    assert corrected.seqs[-2:] == [38, 39]
    off = np.linalg.norm(corrected.poses[-1][:3, 3] - robot.poses[39][:3, 3])
    assert off < 0.1 < 0.3 - 0.1, off  # the 30 cm the robot's frame was off, taken out

    real = RobotMapper.register

    def flaky(self: RobotMapper, seq: int, points: np.ndarray, times: np.ndarray | None = None,
              map_points: np.ndarray | None = None) -> Any:
        if seq == 29:
            raise RuntimeError("no points left")
        return real(self, seq, points, times, map_points)

    broken = edge()
    monkeypatch.setattr(RobotMapper, "register", flaky)
    broken.continue_from(None, *no_pose, [(i, SCANS[i]) for i in range(20, 34)])
    assert broken.backfilled == 9 and broken.backfill_unused == 5 and broken.last_seq == 28
    assert list(broken.backfilled_seqs) == list(range(20, 29))  # which: the edge writes them out
    assert list(posed.backfilled_seqs) == list(range(26, 34)) and not far.backfilled_seqs


def test_a_robots_estimate_from_a_slow_attach_is_moved_as_its_handed_over_poses_were() -> None:
    """The robot's own odometry drifted over an outage (here its frame is 4 m and 30 degrees off the
    edge's), it handed the outage over as a backfill, and the attach took ten scans, read in a turn
    and mapped by the robot alone. The edge's backfill corrects the robot's poses into its own
    frame; the first scan it gets after the attach carries the robot's pose of the scan before it
    (``Scan.prior``), in the frame of the handed-over poses, so the edge moves it by the same
    correction: 0.09-0.12 m off over the next three scans. Taken as sent they are 4.1 m off (the
    edge's own guess, the motion before the turn stretched over eleven scans, does not win
    either). KITTI-360 ping-pong, ``cellular-heldout``, where the robot sent no estimate after a
    slow attach: 7.4 m off at the scans after one (2026-12-07)."""
    start, lost, back, live = 760, 770, 786, 796
    raw = {i: SRC.read(i) for i in range(start, live + 3)}

    def error(pose: np.ndarray, i: int) -> float:  # both frames start at scan ``start``
        truth = np.linalg.inv(raw[start].gt_pose) @ raw[i].gt_pose
        return float(np.linalg.norm(pose[:3, 3] - truth[:3, 3]))

    robot = RobotMapper(voxel_size=0.8, max_range=SRC.max_range)  # the robot's coarse odometry
    for i in range(start, live):
        robot.register(i, raw[i].points)
    drift = _yaw(np.radians(30.0))
    drift[:2, 3] = (4.0, -1.0)
    mine = {i: drift @ robot.poses[i - start] for i in range(start, live)}  # its poses, drifted
    seqs = np.arange(lost, back)
    backfill = [(i, voxel_downsample(raw[i].points, 0.8)) for i in seqs]
    prior = mine[live - 1], robot.odometry.last_delta
    runs = {}
    for moved in (True, False):
        m = RobotMapper(voxel_size=0.4, max_range=SRC.max_range)
        for i in range(start, lost):
            m.register(i, voxel_downsample(raw[i].points, 0.1))
        m.continue_from(None, seqs, np.stack([mine[i] for i in seqs]), backfill,
                        np.stack([mine[i] for i in seqs]))
        assert m.backfilled == back - lost and m.last_seq == back - 1
        if not moved:
            m._handover = None  # as before: the estimate taken in the frame it was sent in
        else:  # an older robot's (frame not said): moved too, the one as sent another guess
            assert m.predict_from(live, live - 1, *prior, contest=True)
            assert m._prior is not None and m._prior[4] is not None and m._prior[4][0] == "prior_unmoved"
            assert m.priors_moved == 1  # (the edge counts them)
            unsaid = m._prior[2]
            assert np.linalg.norm(unsaid[:3, 3] - prior[0][:3, 3]) > 3.0
        assert m.predict_from(live, live - 1, *prior, contest=True, frame=1)  # the robot says (v11)
        if moved:
            assert m._prior is not None and m._prior[4] is None and np.allclose(m._prior[2], unsaid)
        regs = [m.register(i, voxel_downsample(raw[i].points, 0.1)) for i in range(live, live + 3)]
        runs[moved] = ([error(r.pose, i) for r, i in zip(regs, range(live, live + 3), strict=True)],
                       regs[0].gap_motion)
        if moved:
            # after the attach's first live scan, an estimate is in this mapper's frame (a bridge
            # begun from its answers): taken as sent, the moved one is the other guess
            pose = m.poses[-1] @ robot.odometry.last_delta
            assert m.predict_from(live + 5, live + 4, pose, robot.odometry.last_delta, contest=True)
            assert m._prior is not None and np.array_equal(m._prior[2], pose)
            assert m._prior[4] is not None and m._prior[4][0] == "prior_moved"
            # the robot says which (v11): its answers' frame taken as sent, no other guess
            assert m.predict_from(live + 5, live + 4, pose, robot.odometry.last_delta, contest=True, frame=0)
            assert m._prior is not None and np.array_equal(m._prior[2], pose) and m._prior[4] is None
            assert m.priors_moved == 2  # (the frame=1 one above moved too; this one not)
    (errors, kept), (unmoved, _) = runs[True], runs[False]
    assert max(errors) < 0.25 and kept == "prior", (errors, kept)
    assert min(unmoved) > 1.0, unmoved
