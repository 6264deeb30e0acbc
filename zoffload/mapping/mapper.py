"""One robot's map on the edge: KISS-ICP odometry plus a global registered map.

Scans lost on the way (a gap in the sequence numbers) stretch KISS-ICP's constant-velocity
prediction over the gap; without it, one lost second of a moving robot derails the odometry.
Over a gap the robot may also have stopped or reversed, and from a constant-velocity guess metres
off KISS-ICP converges to a wrong place along a street, where the scan still half fits: a scan
after a gap is registered from three guesses (the motion kept, stopped, reversed, see
``GAP_MOTIONS``) and the one whose result overlaps the local map best is kept; the kept motion
wins unless another overlaps by ``GAP_MARGIN`` more. A guess within KISS-ICP's reach of the
first is tried only when the best result so far finds less than ``GAP_LOST`` of the scan in the
map (ICP from a guess tens of degrees off in a turn settles in the wrong place even within
its correspondence distance), and so are the turned guesses: the first turned left and right by
the robot's fastest turn yet over the gap and half of it (``TURN_FACTORS``).

A mapper can continue another's trajectory (``continue_from``): seeded from a checkpoint
(mapping/checkpoint.py), its poses stay in the checkpoint's frame, and the poses the robot
estimated itself since then join its trajectory (the next scan's gap counts from the last of them).

KISS-ICP fixes its voxel size at construction and downsamples every frame again internally (at
0.5x and 1.5x that size). The edge sizes it so the robot's own downsampling never makes the
mapper's grids finer than the data: ``voxel = max(max_range / 100, 2 * robot voxel_max)``
(KISS-ICP's own default is max_range / 100). KISS-ICP's local map forgets points beyond
``max_range``; the global map kept here does not, and is what "map points" counts.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from zoffload.mapping.checkpoint import config_matches, seed
from zoffload.mapping.se3 import as_rigid, se3_power
from zoffload.mapping.voxel import KEY_BITS, KEY_OFFSET, MAX_INDEX, voxel_downsample
from zoffload.mapping.voxelset import VoxelSet

if TYPE_CHECKING:
    from zoffload.protocol import wire

log = logging.getLogger("zoffload.mapping")


@dataclass(frozen=True)
class Registration:
    pose: np.ndarray  # 4x4, first registered scan = identity
    keypoints: int  # points KISS-ICP aligned against its local map
    sigma: float  # adaptive threshold after this scan
    map_points: int
    proc_time: float  # seconds of registration on the edge (ICP + global map)
    icp_time: float  # seconds of KISS-ICP alone
    gap_motion: str = ""  # after a gap, the guess kept: GAP_MOTIONS' names, "turned_left" or "turned_right"


# The guesses a scan after a gap is registered from: the motion per period over the gap times
# these factors (kept: the constant-velocity model; stopped; reversed)
GAP_MOTIONS = (("kept", 1.0), ("stopped", 0.0), ("reversed", -1.0))
# The share of the scan's points in the map another guess's result must add to win: the real
# cases seen (a turn back, a stop) won by 0.39-0.52; under a loaded edge with 5-14 lost scans,
# guesses that all missed differed by 0.05-0.16, where switching is a coin toss
GAP_MARGIN = 0.2
# A result that finds less than this share of the scan's points in the map has failed: every
# guess is tried then, those within ICP's reach of the first too (a satellite run's scan 343,
# three periods after the last in a turn's onset: the kept guess's result 0.13, wrong guesses
# 0.09-0.22, right results of gap scans in the same stretch 0.75-0.88)
GAP_LOST = 0.5
# The turned guesses: the first turned left and right by these fractions of the robot's fastest
# yaw per period yet (``RobotMapper.turn_rate``) times the gap, at most TURN_MAX radians
TURN_FACTORS = (0.5, 1.0)
TURN_MAX = np.radians(90.0)
TURN_MIN = np.radians(1.0)  # a turned guess closer to the first than this is not tried
# The fastest yaw per period a registration may teach: beyond it a pair of poses is a wrong
# registration, not a turn
TURN_RATE_MAX = np.radians(30.0)
# The farthest a robot's estimate may say it moves in one scan period (``predict_from``, from the
# network): 30 m, 300 m/s at 10 Hz; an estimate beyond it or ``TURN_RATE_MAX`` is not taken
STEP_MAX = 30.0
# ICP iterations for the other guesses (KISS-ICP's own limit is 500): from a guess that is wrong
# ICP wanders for hundreds of iterations, and the winner is refined by the full registration
GAP_PROBE_ITERATIONS = 30
# A backfill (``continue_from``) whose first scan comes more than this many scans after the
# mapper's last, with no pose of the robot's to predict it from, is left: over a longer gap the
# robot's pose hand-over is the better guess than constant velocity
BACKFILL_GAP = 3
# The seqs of backfilled scans a mapper remembers (``backfilled_seqs``, written with the edge's
# counters: which of a robot's outage scans its trajectory registered, not just how many)
BACKFILL_SEQS_KEPT = 100_000
# A backfilled scan is registered from a grid of this many times the mapper's voxel and mapped
# with all its points: the robot sends its backfill finer where its link has room (a quarter of its
# odometry's voxel, which is twice the mapper's with KISS-ICP's defaults). Registered as sent, the
# simulator's 0.2 m scans held the robot's worker twice as long (35 scans in 1.0 s against 0.5;
# its next scans queued, dropped) and the `deadzone` runs' trajectories came out worse (0.332 +-
# 0.010 m); from twice the voxel (the grid backfills came at before) the worker's time was as
# before but 50 consecutive scans registered 2-3x farther from the ground truth than from the
# voxel itself (benchmarks/bench_backfill.py); from the voxel, deadzone 0.288 +- 0.021 m, its
# worker 0.6-1.0 s a dead zone (2026-12-06)
BACKFILL_REGISTER_GRID = 1.0


Guesses = list[tuple[str, np.ndarray]]


def _yaw(angle: float) -> np.ndarray:
    """A rotation by ``angle`` radians about the z axis, as a 4x4 pose."""
    m = np.eye(4)
    c, s = np.cos(angle), np.sin(angle)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def _yaw_of(pose: np.ndarray) -> float:
    """How far ``pose`` turns about the z axis, radians (0 to pi)."""
    return abs(float(np.arctan2(pose[1, 0], pose[0, 0])))


def _cell_keys(points: np.ndarray, cell: float) -> np.ndarray:
    """Packed keys of the ``cell``-sized cubes the points fall in (indices clipped to the packing)."""
    idx = np.clip(np.floor(points / cell), -MAX_INDEX, MAX_INDEX).astype(np.int64) + KEY_OFFSET
    return (idx[:, 0] << (2 * KEY_BITS)) | (idx[:, 1] << KEY_BITS) | idx[:, 2]


def map_overlap(points: np.ndarray, pose: np.ndarray, map_keys: np.ndarray, cell: float) -> float:
    """The share of ``points`` (sensor frame) that, placed at ``pose``, fall in a cell of the map
    (``map_keys``: the sorted ``_cell_keys`` of its points, duplicates allowed)."""
    if len(points) == 0 or len(map_keys) == 0:
        return 0.0
    keys = _cell_keys(points @ pose[:3, :3].T + pose[:3, 3], cell)
    at = np.minimum(np.searchsorted(map_keys, keys), len(map_keys) - 1)
    return float(np.mean(map_keys[at] == keys))


def mapper_voxel_size(max_range: float, robot_voxel_max: float, configured: float | None = None) -> float:
    """The KISS-ICP voxel size the edge uses for a robot (see module docstring)."""
    if configured is not None:
        return configured
    return max(max_range / 100.0, 2.0 * robot_voxel_max)


def load_kiss_icp() -> tuple[Any, Any]:
    try:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("the edge mapper needs kiss-icp: pip install 'zoffload[edge]'") from exc
    return KISSConfig, KissICP


def guess_distance(a: np.ndarray, b: np.ndarray, r: float) -> float:
    """How far apart two poses put a point ``r`` metres from the sensor, as KISS-ICP's adaptive
    threshold measures a model's error (there with ``max_range``): the translation between them
    plus the chord the rotation between them moves the point through (``2 r sin(angle / 2)``)."""
    d = np.linalg.inv(a) @ b
    cos = float(np.clip((np.trace(d[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
    return float(np.linalg.norm(d[:3, 3]) + 2.0 * r * np.sin(np.arccos(cos) / 2.0))


def deskew_times(times: np.ndarray | None, n: int) -> np.ndarray:
    """Per-point times as KISS-ICP's deskewing takes them: float64 in [0, 1] over the scan (the
    fraction every KISS-ICP version understands: up to 1.2.1 it expected them normalised, from
    1.2.2 it normalises them itself). An empty array (no deskew) when there are none or they do
    not spread: KISS-ICP 1.3 aborts the process (SOPHUS_ENSURE) on all-equal times.
    ``ValueError`` when there is not one finite time per point."""
    if times is None or n == 0:
        return np.empty(0)
    t = np.asarray(times, np.float64).reshape(-1)
    if len(t) != n:
        raise ValueError(f"{len(t)} point times for {n} points")
    if not np.isfinite(t).all():
        raise ValueError("non-finite point times")
    lo, hi = float(t.min()), float(t.max())
    if not hi > lo:
        return np.empty(0)
    return (t - lo) / (hi - lo)


MOTION_SPAN = 3  # scans the motion per scan is averaged over when a trajectory is handed over


def motion_per_scan(seqs: np.ndarray, poses: np.ndarray, anchor: tuple[int, np.ndarray] | None = None,
                    max_gap: int = 50, span: int = MOTION_SPAN) -> np.ndarray | None:
    """KISS-ICP's ``last_delta`` (the motion of one scan period, in the body frame) from a handed-over
    trajectory: the newest pose against the oldest one at most ``span`` scans before it (among
    ``poses`` and ``anchor``, the pose the trajectory starts from), divided by their gap; None
    with nothing to compare or a gap over ``max_gap``. Averaged over a few scans: the poses come
    from the robot's coarse odometry, whose scan-to-scan steps are noisy."""
    pairs = ([anchor] if anchor is not None else []) + list(zip(seqs.tolist(), poses, strict=True))
    if len(pairs) < 2:
        return None
    last_seq, last = pairs[-1]
    earlier = [(s, p) for s, p in pairs[:-1] if 0 < last_seq - s <= span] or [pairs[-2]]
    first_seq, first = earlier[0]
    gap = int(last_seq) - int(first_seq)
    if not 0 < gap <= max_gap:
        return None
    return as_rigid(se3_power(np.linalg.inv(first) @ last, 1.0 / gap))


class RobotMapper:
    """KISS-ICP odometry and a global map for one robot."""

    def __init__(
        self,
        voxel_size: float,
        max_range: float,
        min_range: float = 0.0,
        max_points_per_voxel: int = 20,
        deskew: bool = False,
        map_resolution: float = 0.1,
        max_gap: int = 50,
        gap_motions: tuple[tuple[str, float], ...] = GAP_MOTIONS,
        turn_factors: tuple[float, ...] | None = None,
    ) -> None:
        KISSConfig, KissICP = load_kiss_icp()
        config = KISSConfig()
        config.data.max_range = max_range
        config.data.min_range = min_range
        config.data.deskew = deskew
        config.mapping.voxel_size = voxel_size
        config.mapping.max_points_per_voxel = max_points_per_voxel
        self.config = config
        self.odometry = KissICP(config)
        # One point per map voxel, never forgotten: the registered global map.
        self.global_map = VoxelSet(map_resolution)
        self.map_resolution = map_resolution
        self.voxel_size = voxel_size
        self.max_gap = max_gap  # beyond this many lost scans, constant velocity means nothing
        self.deskew = deskew
        self.gap_motions = gap_motions  # the guesses a scan after a gap is registered from
        # and the turned ones (None: TURN_FACTORS; empty: no turned guesses)
        self.turn_factors = TURN_FACTORS if turn_factors is None else turn_factors
        self.turn_rate = 0.0  # the fastest yaw per period yet between registered scans (rad; a gap: its mean)
        from kiss_icp.registration import Registration as IcpRegistration

        self._probe = IcpRegistration(  # the other guesses' ICP, bounded
            max_num_iterations=GAP_PROBE_ITERATIONS,
            convergence_criterion=config.registration.convergence_criterion,
            max_num_threads=config.registration.max_num_threads)
        self.seqs: list[int] = []  # the trajectory: registered scans and the robot's own poses
        self.poses: list[np.ndarray] = []
        self.last_seq: int | None = None  # the scan the odometry's last pose belongs to
        self.registered = 0  # scans registered here (the trajectory also holds the robot's poses)
        self.after_gap = 0  # of them, scans after a gap
        self.guessed = 0  # of those, registered from more than one guess (_register_after_gap)
        # A robot's estimate for a scan, contested (``predict_from``): (seq, prior_seq, pose, motion
        # per scan, the same estimate in the other frame (name, pose) or None), taken by that
        # scan's ``register``
        self._prior: tuple[int, int, np.ndarray, np.ndarray, tuple[str, np.ndarray] | None] | None = None
        # The last attach (``continue_from``): how it moved the robot's poses into this mapper's
        # frame (the correction its backfill found; identity without one), and the first scan
        # registered after it (None until then): a robot's estimate of a scan before that one is
        # in the frame of the poses it handed over (``predict_from``)
        self._handover: np.ndarray | None = None
        self.priors_moved = 0  # contested estimates taken moved by the handover's correction
        self._live_from: int | None = None
        self.turned = 0  # of those, registered from a turned guess
        self.backfilled = 0  # scans registered from an attach's backfill (continue_from)
        self.backfilled_seqs: deque[int] = deque(maxlen=BACKFILL_SEQS_KEPT)  # which, the newest
        self.backfill_unused = 0  # backfilled scans not registered (no earlier state, or too old)
        self.backfill_posed = 0  # backfills whose first scan was predicted from their own poses (v10)

    def backfill_points(self, points: np.ndarray) -> np.ndarray:
        """What a backfilled scan is registered from: its points at ``BACKFILL_REGISTER_GRID``
        times the mapper's voxel (the global map takes all of them)."""
        return voxel_downsample(points, BACKFILL_REGISTER_GRID * self.voxel_size) if len(points) else points

    def register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None,
                 map_points: np.ndarray | None = None) -> Registration:
        """Register one scan; ``times`` (per point, seconds, any offset) deskew it when the
        mapper was made with ``deskew`` (see ``deskew_times``); ``map_points`` (the scan's frame,
        no per-point times): what the global map grows by instead of ``points``. A robot's
        estimate ``predict_from`` took, contested, for this scan is applied here, and undone if
        the registration fails (another scan's is dropped)."""
        prior, self._prior = self._prior, None
        if prior is None or prior[0] != int(seq):
            reg = self._register(seq, points, times, map_points)
        else:
            odo = self.odometry
            own = (odo.last_pose.copy(), odo.last_delta.copy(), self.last_seq)
            _, prior_seq, pose, delta, other = prior
            self._take(prior_seq, pose, delta)
            alt = None  # the estimate in the other frame: where it would put this scan
            if other is not None:
                alt = (other[0], as_rigid(other[1] @ se3_power(delta, int(seq) - prior_seq)))
            try:
                reg = self._register(seq, points, times, map_points, (*own, delta), alt)
            except BaseException:
                odo.last_pose, odo.last_delta, self.last_seq = own
                raise
        if self._live_from is None:
            self._live_from = int(seq)  # (``continue_from`` sets it None after its backfill)
        return reg

    def _register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None,
                  map_points: np.ndarray | None = None,
                  own: tuple[np.ndarray, np.ndarray, int | None, np.ndarray] | None = None,
                  alt: tuple[str, np.ndarray] | None = None) -> Registration:
        """``register``; ``own``: this mapper's pose, motion per scan and last seq before a
        contested estimate of the robot's was taken for this scan, and the robot's motion;
        ``alt``: that estimate's guess for this scan in the other frame (``predict_from``)."""
        t0 = time.perf_counter()
        # row-major: KISS-ICP's binding converts any other layout point by point (hundreds of times slower)
        frame = np.ascontiguousarray(points, dtype=np.float64)
        stamps = deskew_times(times, len(frame)) if self.deskew else np.empty(0)
        # Scans lost on the way: KISS-ICP predicts one scan period of motion, so stretch its
        # constant-velocity model over the gap, and bring it back to one period afterwards.
        gap = int(seq) - self.last_seq if self.last_seq is not None else 1
        stretch = 1 < gap <= self.max_gap
        contested = own is not None
        own_guess = self._own_guess(int(seq), own)
        others = [g for g in (alt, own_guess) if g is not None]
        previous = self.odometry.last_pose.copy()
        if (stretch or contested) and len(stamps):
            # Deskew with one period of motion (the sweep's), not the stretched prediction
            frame = self.odometry.preprocessor.preprocess(frame, stamps, self.odometry.last_delta)
            stamps = np.empty(0)
        after_gap = (stretch or contested) and not self.odometry.local_map.empty()
        self.after_gap += after_gap
        gap_motion = ""
        if after_gap:
            guesses, spare = self._gap_guesses(gap, frame, others, contested)
            keypoints, gap_motion = self._register_after_gap(int(seq), frame, gap, guesses, spare)
        else:
            if stretch:
                self.odometry.last_delta = as_rigid(se3_power(self.odometry.last_delta, gap))
            # Run KISS-ICP (it returns the scan deskewed, which is what the global map keeps)
            frame_out, keypoints = self.odometry.register_frame(frame, stamps)
            if len(stamps):
                frame = np.asarray(frame_out)
            if stretch:
                self.odometry.last_delta = as_rigid(se3_power(self.odometry.last_delta, 1.0 / gap))
        icp_time = time.perf_counter() - t0
        pose = self.odometry.last_pose.copy()
        if own is not None:
            # The motion on from here: not from the pose one period before the robot's estimate
            # (where its pose was off, the registration's correction of it would become a
            # velocity of metres a scan) but the robot's own motion per scan where its estimate
            # won, else the motion from this mapper's own last scan (within ``max_gap``)
            own_pose, _, before, robot_delta = own
            if gap_motion == "" or gap_motion.startswith("prior"):
                previous, gap = pose @ np.linalg.inv(robot_delta), 1
                self.odometry.last_delta = robot_delta
            elif own_guess is not None and before is not None:  # (its last scan within max_gap)
                previous, gap = own_pose, int(seq) - before
                self.odometry.last_delta = as_rigid(se3_power(np.linalg.inv(previous) @ pose, 1.0 / gap))
            if gap_motion == "own":  # (counted by the edge: gap_own)
                log.info("scan %d: the robot's estimate of its pose lost to this mapper's own guess", seq)
        if 1 <= gap <= self.max_gap and self.last_seq is not None:  # the yaw per period since the last
            d = np.linalg.inv(previous) @ pose
            yaw = _yaw_of(d) / gap
            if yaw <= TURN_RATE_MAX:
                self.turn_rate = max(self.turn_rate, yaw)
        # Grow the global map with the scan in world coordinates
        self.global_map.add(frame if map_points is None else np.asarray(map_points, np.float64), pose)
        self.seqs.append(int(seq))
        self.poses.append(pose)
        self.last_seq = int(seq)
        self.registered += 1
        return Registration(
            pose=pose,
            keypoints=int(len(keypoints)),
            sigma=float(self.odometry.adaptive_threshold.get_threshold()),
            map_points=len(self.global_map),
            proc_time=time.perf_counter() - t0,
            icp_time=icp_time,
            gap_motion=gap_motion,
        )

    def _own_guess(self, seq: int, own: tuple[np.ndarray, np.ndarray, int | None, np.ndarray] | None
                   ) -> tuple[str, np.ndarray] | None:
        """This mapper's own constant-velocity guess for ``seq`` when the robot's estimate was
        taken for it (``own``: what it replaced), within ``max_gap`` of its last scan."""
        if own is None:
            return None
        pose, delta, last, _ = own
        if last is None or not 0 < seq - last <= self.max_gap:
            return None
        return "own", pose @ as_rigid(se3_power(delta, seq - last))

    def _take(self, prior_seq: int, pose: np.ndarray, delta: np.ndarray) -> None:
        """Predict the next scans from the robot's estimate: the pose one period before it, so
        that ``register`` stretches the motion over (seq - prior_seq + 1) periods from there."""
        self.odometry.last_pose = as_rigid(np.asarray(pose, np.float64) @ np.linalg.inv(delta))
        self.odometry.last_delta = delta
        self.last_seq = int(prior_seq) - 1

    def _gap_guesses(self, gap: int, frame: np.ndarray, others: Sequence[tuple[str, np.ndarray]] = (),
                     prior: bool = False) -> tuple[Guesses, Guesses]:
        """The initial guesses for a scan ``gap`` periods after the last one, in two lists: the
        first of ``gap_motions`` and each other that moves the scan's points farther from where
        the first puts them than KISS-ICP's correspondence distance (3 sigma), tried in turn; and
        the spare ones, tried only when those all failed (``GAP_LOST``): the other motions within
        that reach, and the turned guesses (the first turned left and right about the sensor's z
        axis by ``turn_factors`` x the gap x ``turn_rate``: a ground robot's turn).
        How far apart: the translation plus the chord the rotation apart moves a point at the
        scan's median range through (``guess_distance``). Translation alone missed a turn: in the
        simulator's sharpest one (yaw +5.4 degrees a scan, then swinging back at -4.2) a scan two
        periods after the last was guessed 19 degrees past where the robot was, which moves a
        point 10 m away by 1.9 m against a reach of 1.4; the other guesses, a few centimetres
        from that one in translation, were never tried, and ICP settled 16 degrees off for the
        rest of the run. The median range, not ``max_range`` (KISS-ICP's own model error): at 40 m
        a turn of 2 degrees is out of reach, and trying the other guesses on every gap in a turn
        costs the edge time that holds the robot's window (README, "Lost scans"). Within reach is
        not always reached: after a few gaps sigma grows (1.6 m: a reach of 4.8 m), and at a
        turn's onset three periods after the last scan ICP settled 20 degrees off from a kept
        guess 2.9 m from the right one; those are the spare guesses.
        ``prior``: the first guess is the robot's estimate (``predict_from``, contested; named
        "prior"), and ``others`` more of the others: this mapper's own guess ("own") and the
        estimate in the other frame of an attach ("prior_moved" or "prior_unmoved", ``predict_from``).
        The robot's odometry can be wrong (a gap in a turn), and an edge that took its estimate as
        it was jumped 3 m at the scan that carried it (the simulator's ``wifi-locations``, scan 358
        of a run on 2026-12-07: 0.06 m off before it, 5.2 m at the run's end)."""
        odo = self.odometry
        sigma = odo.adaptive_threshold.get_threshold()
        motions = [(name, odo.last_pose @ as_rigid(se3_power(odo.last_delta, gap * factor)))
                   for name, factor in self.gap_motions] + list(others)
        if prior:
            motions[0] = ("prior", motions[0][1])
        first = motions[0][1]
        reach = 3 * sigma
        ranges = np.linalg.norm(frame[:, :3], axis=1)
        within = ranges[ranges <= self.config.data.max_range]
        r = float(np.median(within)) if len(within) else 0.0
        far = [guess_distance(first, g, r) > reach for _, g in motions[1:]]
        guesses = motions[:1] + [m for m, f in zip(motions[1:], far, strict=True) if f]
        spare = [m for m, f in zip(motions[1:], far, strict=True) if not f]
        for factor in self.turn_factors:
            angle = min(TURN_MAX, factor * gap * self.turn_rate)
            if angle >= TURN_MIN:
                spare += [("turned_left", first @ _yaw(angle)), ("turned_right", first @ _yaw(-angle))]
        return guesses, spare

    def _register_after_gap(self, seq: int, frame: np.ndarray, gap: int, guesses: Guesses,
                            spare: Guesses) -> tuple[np.ndarray, str]:
        """KISS-ICP's ``register_frame`` for a scan ``gap`` periods after the last one, from each
        of ``guesses`` and, when the best of their results overlaps the local map by less than
        ``GAP_LOST``, of ``spare`` (``_gap_guesses``); keeps the result that overlaps the local map
        best (the first unless another adds ``GAP_MARGIN``, so once a result overlaps by
        ``1 - GAP_MARGIN`` no other guess is tried). ``frame`` is deskewed already.
        Returns the points aligned and the name of the guess kept."""
        odo = self.odometry
        frame = odo.preprocessor.preprocess(frame, np.empty(0), odo.last_delta)  # the range limits
        source, frame_down = odo.voxelize(frame)
        sigma = odo.adaptive_threshold.get_threshold()
        cell = 0.5 * self.voxel_size
        scored = len(guesses) > 1 or bool(spare)
        # sorted, duplicates left in: np.unique (hashing, numpy 2.4) took 3-5x as long on a local map
        map_keys = np.sort(_cell_keys(odo.local_map.point_cloud(), cell)) if scored else np.empty(0)
        best: tuple[float, str, np.ndarray, np.ndarray] | None = None
        kept, tried = 0.0, 0
        for i, (name, guess) in enumerate([*guesses, *spare]):
            if i == len(guesses) and best is not None and best[0] >= GAP_LOST:
                break  # the spare guesses only after a failure
            pose = (odo.registration if i == 0 else self._probe).align_points_to_map(
                points=source, voxel_map=odo.local_map, initial_guess=guess,
                max_correspondance_distance=3 * sigma, kernel=sigma)
            tried += 1
            overlap = map_overlap(source, pose, map_keys, cell) if scored else 1.0
            if best is None:
                kept = overlap
            if best is None or overlap > best[0] + GAP_MARGIN:
                best = (overlap, name, guess, pose)
            if best[0] >= 1.0 - GAP_MARGIN:
                break  # no other guess can beat it by the margin
        assert best is not None
        self.guessed += tried > 1
        _, name, guess, pose = best
        if name != guesses[0][0]:  # converge fully from where the bounded probe got
            self.turned += name.startswith("turned")
            pose = odo.registration.align_points_to_map(
                points=source, voxel_map=odo.local_map, initial_guess=pose,
                max_correspondance_distance=3 * sigma, kernel=sigma)
        # KISS-ICP's update step, with the deviation from the guess kept
        odo.adaptive_threshold.update_model_deviation(np.linalg.inv(guess) @ pose)
        odo.local_map.update(frame_down, pose)
        odo.last_delta = as_rigid(se3_power(np.linalg.inv(odo.last_pose) @ pose, 1.0 / gap))
        odo.last_pose = pose
        if name != guesses[0][0]:
            log.info("scan %d after a %d-scan gap registered from the guess %r: %.0f %% of its points in "
                     "the local map, %.0f %% from the motion kept", seq, gap, name, 100 * best[0], 100 * kept)
        return source, name

    def continue_from(self, checkpoint: wire.Checkpoint | None, local_seqs: np.ndarray,
                      local_poses: np.ndarray, backfill: Sequence[tuple[int, np.ndarray]] = (),
                      backfill_poses: np.ndarray | None = None) -> bool:
        """Continue a trajectory: the odometry is (re-)seeded from ``checkpoint`` when it is newer
        than the last scan this mapper knows (the local map replaced by the checkpoint's; a mapper
        that has mapped the robot keeps its own local map against the robot's own checkpoint, or
        one of a mapper configured otherwise, and takes only its pose and motion), then
        the robot's own poses after that join the trajectory and the last of them becomes the
        odometry's pose. The global map is kept, and the checkpoint's turn rate is taken when it
        is the faster (a mapper taking over in a turn learns it only from the turn's next scans).
        Returns whether the odometry was seeded.

        ``backfill`` (seq, points), ascending: the scans the robot registered itself while no edge
        mapped it, at a coarse grid. A mapper that mapped the robot before and whose last scan is
        close enough before the first newer one (``_backfill``) registers them in order instead
        of taking the checkpoint's pose and the robot's poses they cover; the robot's poses after
        them join the trajectory moved by the correction found for the last. Registered across
        the outage against its own local map, a scan after seconds of driving left the trajectory
        +30 % of local's over the same scans where the backfilled replays had −0 to +9 %, even
        from the ground truth's pose (``cellular-heldout``, offline replays; README, Fleet).
        ``backfill_poses`` (version 10): the robot's pose of each backfilled scan, in the frame of
        its local poses; with them the first can be predicted after a gap the local poses (those
        after the robot's checkpoint) do not cover."""
        seeded = False
        self._prior = None
        self._handover = np.eye(4)
        if checkpoint is not None:  # the turn rate the last mapper learnt (version 8; 0: not said)
            self.turn_rate = max(self.turn_rate, min(float(checkpoint.turn_rate), TURN_RATE_MAX))
        carried = self._backfill(backfill, local_seqs, local_poses, backfill_poses) if backfill else None
        if carried is not None:
            checkpoint = None  # its pose is the robot's, drifted; the backfill has carried this mapper on
            # the robot's poses after it, moved as the backfill's last was, and that correction
            local_seqs, local_poses, self._handover = carried
        self._live_from = None  # (the backfill's registrations are not live scans)
        if checkpoint is not None and (self.last_seq is None or checkpoint.seq > self.last_seq):
            matches = config_matches(self.odometry, checkpoint)
            if (not matches or not checkpoint.edge) and self.last_seq is not None:
                # The robot's own checkpoint (its local odometry; edge "") or one of a mapper
                # configured otherwise, back on an edge that mapped it before: keep this mapper's
                # local map (same world frame, registered here), take the pose. Whatever the robot's
                # voxel: a local odometry at the edge's own voxel matched its configuration, and its
                # map, drifted over the outage, replaced the edge's (cellular-heldout: trajectory
                # +68 % of local's over the same scans against +16 %, one run each; README, Fleet)
                maker = "the robot's own odometry" if not checkpoint.edge else "a mapper configured otherwise"
                log.info("checkpoint of %s from %s (voxel %.3f m): keeping this mapper's local map, "
                         "continuing from its pose", checkpoint.robot, maker, checkpoint.voxel_size)
                self.odometry.last_pose = as_rigid(checkpoint.pose)
                self.odometry.last_delta = as_rigid(checkpoint.delta)  # the robot's motion, not ours
            else:
                if not matches:
                    log.warning("checkpoint of %s made by a mapper configured otherwise (voxel %.3f m, "
                                "range %.1f m): seeding anyway", checkpoint.robot, checkpoint.voxel_size,
                                checkpoint.max_range)
                if self.last_seq is not None:
                    self.odometry.local_map.clear()
                seed(self.odometry, checkpoint)
                seeded = True
            self.last_seq = int(checkpoint.seq)
        seqs = np.asarray(local_seqs, np.int64).reshape(-1)
        poses = np.asarray(local_poses, np.float64).reshape(-1, 4, 4)
        start = self.last_seq
        newer = seqs > (start if start is not None else -1)
        for s, p in zip(seqs[newer], poses[newer], strict=True):
            self.seqs.append(int(s))
            self.poses.append(p.copy())
        if newer.any():
            # The constant-velocity model continues the robot's own motion: after seconds away, the
            # motion this mapper saw last may be long over (stopped, turned, reversed), and stretched
            # over the next gap it would put the next scan metres off
            anchor = (start, np.array(self.odometry.last_pose, np.float64)) if start is not None else None
            delta = motion_per_scan(seqs[newer], poses[newer], anchor, self.max_gap)
            if delta is not None:
                self.odometry.last_delta = delta
            self.odometry.last_pose = as_rigid(poses[newer][-1])
            self.last_seq = int(seqs[newer][-1])
        return seeded

    def _backfill(self, backfill: Sequence[tuple[int, np.ndarray]], local_seqs: np.ndarray,
                  local_poses: np.ndarray, backfill_poses: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Register the backfill's scans newer than this mapper's last (``continue_from``); the
        first, after scans this mapper missed, from the robot's own pose of it when the robot
        handed one over (``predict_from``), else only within ``BACKFILL_GAP`` scans (constant
        velocity); farther, from the robot's pose of that scan in ``backfill_poses`` (version 10;
        its motion from its poses of the next few), else the backfill is left (the robot's pose
        hand-over is the better guess than constant velocity). Within ``BACKFILL_GAP`` the
        backfill's poses are not used: constant velocity from this mapper's own state was the
        measured choice there (2026-12-06: predicted from the robot's pose instead, the simulator's
        ``cellular-heldout`` trajectory came out +2 ± 6 % of local's over the same scans in three
        runs, against −5 ± 1 % in three without).
        A registration that fails ends it there (the rest left unused). Returns the robot's poses
        after the last scan registered, moved by the correction this mapper found for it (the
        robot's pose of that scan against its own), and that correction; or None when nothing was
        registered.
        """
        last = self.last_seq
        newer = [(int(s), p) for s, p in backfill if last is not None and int(s) > last]
        if last is None or not newer:
            self.backfill_unused += len(backfill)
            return None
        seqs = np.asarray(local_seqs, np.int64).reshape(-1)
        poses = np.asarray(local_poses, np.float64).reshape(-1, 4, 4)
        first = newer[0][0]
        mine = np.flatnonzero((seqs > last) & (seqs <= first))
        own = (backfill_poses is not None and len(backfill_poses) == len(backfill)
               and first - last > BACKFILL_GAP and not len(mine))  # the backfill's poses predict it
        if first - last > self.max_gap or (first - last > BACKFILL_GAP and not len(mine) and not own):
            self.backfill_unused += len(backfill)
            return None
        self.backfill_unused += len(backfill) - len(newer)
        if own and backfill_poses is not None:
            # the robot's poses of the backfill's first scan and the next few: its pose, its motion
            k = len(backfill) - len(newer)
            head = np.asarray(backfill_poses[k:k + MOTION_SPAN + 1], np.float64).reshape(-1, 4, 4)
            delta = motion_per_scan(np.array([s for s, _ in newer[:len(head)]], np.int64), head, None,
                                    self.max_gap)
            self.predict_from(first, first, head[0], delta if delta is not None else np.eye(4))
            self.backfill_posed += 1
        elif first - last > 1 and len(mine):
            q = mine[-1]
            anchor = (last, np.array(self.odometry.last_pose))
            delta = motion_per_scan(seqs[mine], poses[mine], anchor, self.max_gap)
            if delta is not None:
                self.predict_from(first, int(seqs[q]), poses[q], delta)
        # the robot's poses of the backfill's scans (version 10): over a gap the robot's ring left
        # between two of them (a ring thinned over a long outage), its motion from one to the next
        robot_of = ({int(s): p for (s, _), p in zip(backfill, backfill_poses, strict=True)}
                    if backfill_poses is not None and len(backfill_poses) == len(backfill) else {})
        done = 0
        for seq, points in newer:
            prev = self.last_seq
            if done and prev is not None and seq - prev > BACKFILL_GAP and {prev, seq} <= robot_of.keys():
                rel = as_rigid(np.linalg.inv(np.asarray(robot_of[prev], np.float64))
                               @ np.asarray(robot_of[seq], np.float64))
                pose = np.asarray(self.odometry.last_pose, np.float64) @ rel
                self.predict_from(seq, seq, pose, as_rigid(se3_power(rel, 1.0 / (seq - prev))))
            try:
                self.register(seq, self.backfill_points(points), map_points=points)
            except Exception as exc:  # a scan KISS-ICP cannot take: the backfill ends before it
                log.warning("backfill scan %d not registered (%s): the %d after it left", seq,
                            str(exc)[:200], len(newer) - done - 1)
                self.backfill_unused += len(newer) - done
                break
            done += 1
            self.backfilled += 1
            self.backfilled_seqs.append(seq)
        if not done:
            return None
        end = self.seqs[-1]
        at = np.flatnonzero(seqs == end)
        robot_end = poses[at[0]] if len(at) else None
        if robot_end is None:
            # the robot's pose of that scan from the backfill's own (its local poses start later)
            robot_end = np.asarray(robot_of[end], np.float64) if end in robot_of else None
        correction = self.poses[-1] @ np.linalg.inv(robot_end) if robot_end is not None else np.eye(4)
        after = seqs > end
        return seqs[after], np.einsum("ij,njk->nik", correction, poses[after]), correction

    def predict_from(self, seq: int, prior_seq: int, pose: np.ndarray, delta: np.ndarray,
                     contest: bool = False, frame: int = -1) -> bool:
        """Take the robot's own estimate (its pose after scan ``prior_seq`` and its motion per scan
        then, in this mapper's world frame) as the prediction for scan ``seq``, when this mapper
        missed scans before ``seq`` that the estimate covers: over a gap the constant-velocity
        model assumes the robot kept the motion it had, and a turn or stop during a second-long
        outage puts the next scan metres off (KISS-ICP then converges to a wrong place). A
        following scan (no gap), an estimate no newer than this mapper's last scan, or one older
        than ``max_gap`` scans is ignored. Returns whether it was taken; the next ``register``
        of ``seq`` predicts ``pose @ delta^(seq - prior_seq)``, and with ``contest`` (a scan's
        ``prior``, from the network) tries this mapper's own guess too (``_gap_guesses``); such
        an estimate whose motion per scan passes ``STEP_MAX`` or ``TURN_RATE_MAX`` is not taken.

        A contested estimate's frame after an attach whose backfill moved the robot's poses
        (``continue_from``): the robot's poses of the scans it read while the attach was under way,
        or of a bridge it began from its own checkpoint before this mapper's reached it, are in
        the frame of the poses it handed over, and are moved by the same correction. ``frame``
        (``Scan.prior_frame``, version 11) is the robot's word: 1 that frame, 0 this mapper's.
        Not said (-1, an older robot), an estimate of a scan before the first registered after
        the attach is moved, and the other frame's version of any is one more guess. Before, the
        robot sent none after a slow attach, and a mapper carried by a backfill to the scan before
        a turn (KITTI-360 replayed ping-pong, ``cellular-heldout``) stretched its motion over the
        five scans read meanwhile: eight scans, 7.4 m, off."""
        last = self.last_seq
        if last is None or seq - last <= 1 or not last < prior_seq <= seq or seq - prior_seq >= self.max_gap:
            return False
        delta = as_rigid(np.asarray(delta, np.float64))
        if contest and (float(np.linalg.norm(delta[:3, 3])) > STEP_MAX
                        or _yaw_of(delta) > TURN_RATE_MAX):
            return False  # no robot moves so (a wrong or hostile estimate): not taken
        if contest:  # taken by the scan's register (not if it never comes, or fails)
            pose, other = np.asarray(pose, np.float64), None
            c = self._handover
            if c is not None and not np.allclose(c, np.eye(4)):
                moved = as_rigid(c @ pose)
                live = self._live_from
                if frame == 1:
                    pose = moved
                elif frame == -1 and (live is None or prior_seq < live):
                    pose, other = moved, ("prior_unmoved", pose)
                elif frame == -1 and live is not None and prior_seq < live + self.max_gap:
                    other = ("prior_moved", moved)  # (a bridge begun before this mapper's answers came)
                self.priors_moved += pose is moved  # (the edge counts them: prior_moved_by_attach)
            self._prior = (int(seq), int(prior_seq), pose, delta, other)
        else:
            self._take(prior_seq, pose, delta)
        return True

    @property
    def map_points(self) -> int:
        return len(self.global_map)

    def map_cloud(self) -> np.ndarray:
        return self.global_map.points().astype(np.float32)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        seqs = np.asarray(self.seqs, np.int64)
        poses = np.asarray(self.poses, np.float64).reshape(-1, 4, 4)
        return seqs, poses
