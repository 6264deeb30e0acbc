"""What the live view logs, and where: one Rerun entity tree per robot, fed decoded wire messages.

Entities (``<id>`` a robot id; time on the ``time`` timeline = the viewer's clock when it logged,
since robot and edge clocks are not synchronised)::

    robots/<id>/map                  Points3D   the edge's registered map (world frame), polled
    robots/<id>/trajectory           LineStrips3D  the poses of the registered scans
    robots/<id>/pose                 Points3D   the latest pose, labelled with the robot id
    robots/<id>/scan                 Points3D   the latest scan, placed by its own ack's pose
    robots/<id>/link/<name>          Scalars    rate_hz (scans acked per second), T_s (inter-arrival
                                                at the edge), rtt_ms, voxel_m, lost, late, edges,
                                                fallback, mbps_out, ping_ms
    robots/<id>/mapping/<name>       Scalars    proc_ms, queue_ms, map_points (from the acks)
    robots/<id>/camera               EncodedImage  the robot's preview of a frame (JPEG)
    robots/<id>/camera/persons       Boxes2D    its person boxes, coloured and labelled by where
                                                the frame was detected (local / edge)
    robots/<id>/perception/<name>    Scalars    on_edge (1 edge, 0 local, per preview),
                                                local_fps, edge_fps, cpu_process, edge_infer_ms
    robots/<id>/edge_frame[/detections]  a frame sent to the edge with the edge's boxes (opt-in)
    edges/<id>/<name>                Scalars    the edge's status values

Pure: no Zenoh, no threads; the caller passes the time. Heavy entities are throttled (scans,
trajectory, frames) and decimated (map, trajectory) so a long session stays bounded in the
viewer's memory.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zoffload.lab.view import rerun
from zoffload.protocol import wire
from zoffload.protocol.keys import ID

TIMELINE = "time"
LOCAL_COLOR = (240, 150, 30)
EDGE_COLOR = (40, 190, 90)
MAP_COLOR = (150, 160, 175)
SCAN_COLOR = (255, 70, 70)
# Robot status value -> link scalar (rate_hz is derived from successive statuses)
LINK_VALUES = {"rtt_ms": "rtt_ms", "voxel": "voxel_m", "lost": "lost", "late": "late",
               "edges": "edges", "fallback": "fallback", "mbps_out": "mbps_out", "ping_ms": "ping_ms"}
MAX_EDGE_VALUES = 64
MAX_COORD = 1e6  # [m] a pose farther out is not one
RATE_WINDOW = 0.5  # [s] of robot clock between the two statuses a rate is taken from


def robot_path(robot: str, *parts: str) -> str:
    return "/".join(("robots", wire.check_id(robot, "robot id"), *parts))


def plausible(pose: np.ndarray) -> bool:
    """A finite rigid transform within MAX_COORD of the origin (the wire only checks finiteness):
    rotation entries within [-1, 1] (with rounding slack), so placing a scan cannot overflow."""
    return bool(np.isfinite(pose).all() and np.abs(pose[:3, :3]).max() <= 1.01
                and np.abs(pose[:3, 3]).max() <= MAX_COORD)


def decimate(points: np.ndarray, limit: int) -> np.ndarray:
    """At most ``limit`` rows, evenly strided (the last row always kept: the newest pose)."""
    if len(points) <= limit:
        return points
    idx = np.linspace(0, len(points) - 1, limit).round().astype(np.int64)
    return points[idx]


@dataclass
class _Robot:
    track: OrderedDict[int, np.ndarray] = field(default_factory=OrderedDict)  # seq -> position
    poses: OrderedDict[int, np.ndarray] = field(default_factory=OrderedDict)  # recent seq -> pose
    pending_scan: tuple[int, np.ndarray] | None = None  # waiting for its ack's pose
    pending_frame: wire.Frame | None = None  # waiting for its detections
    status: wire.Status | None = None
    scan_logged: float = -np.inf
    frame_logged: float = -np.inf
    track_logged: float = -np.inf
    track_dirty: bool = False
    edge_frames: bool = False  # one was logged: the layout shows them


class Recording:
    """Logs decoded wire messages to a ``rerun.RecordingStream`` (see the module docstring)."""

    def __init__(self, stream: Any, scan_period: float = 0.5, trajectory_period: float = 1.0,
                 frame_period: float = 0.5, max_map_points: int = 500_000, max_trajectory: int = 100_000,
                 max_track_vertices: int = 5_000, recent_poses: int = 64) -> None:
        self.rr = rerun()
        self.stream = stream
        self.scan_period, self.trajectory_period = scan_period, trajectory_period
        self.frame_period = frame_period
        self.max_map_points, self.max_trajectory = max_map_points, max_trajectory
        self.max_track_vertices, self.recent_poses = max_track_vertices, recent_poses
        self.robots: dict[str, _Robot] = {}
        self._time = 0.0
        self.stream.log("robots", self.rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    # Robots
    def robot(self, robot: str) -> _Robot:
        """The state of ``robot``; admission (how many, which) is the caller's (feed.py)."""
        state = self.robots.get(robot)
        if state is None:
            state = self.robots[robot] = _Robot()
            self.stream.send_blueprint(self.blueprint(), make_active=True, make_default=True)
        return state

    def blueprint(self) -> Any:
        """The layout: the 3D world of every robot, then per robot its camera and its link."""
        import rerun.blueprint as rrb

        # Entity filters take no wildcard inside a path: each robot's images are left out by name
        hidden = [f"- /{robot_path(rid, part)}/**"
                  for rid in sorted(self.robots) for part in ("camera", "edge_frame")]
        world = rrb.Spatial3DView(origin="/robots", name="world", contents=["+ /robots/**", *hidden])
        per_robot = []
        for rid in sorted(self.robots):
            camera: Any = rrb.Spatial2DView(origin=robot_path(rid, "camera"), name=f"{rid} camera")
            if self.robots[rid].edge_frames:  # --frames: the frame the edge saw beside the preview
                camera = rrb.Horizontal(camera, rrb.Spatial2DView(origin=robot_path(rid, "edge_frame"),
                                                                  name=f"{rid} edge frame"))
            per_robot.append(rrb.Vertical(
                camera,
                rrb.TimeSeriesView(origin=robot_path(rid, "link"), name=f"{rid} link"),
                rrb.TimeSeriesView(origin=robot_path(rid, "perception"), name=f"{rid} perception"),
            ))
        right = rrb.Tabs(*per_robot) if len(per_robot) > 1 else (per_robot[0] if per_robot else None)
        layout = rrb.Horizontal(world, right, column_shares=[3, 2]) if right is not None else world
        # Live: the time cursor follows the newest data (a viewer joining late would replay otherwise)
        return rrb.Blueprint(layout, rrb.BlueprintPanel(state="collapsed"),
                             rrb.SelectionPanel(state="collapsed"),
                             rrb.TimePanel(state="collapsed", timeline=TIMELINE, play_state="following"))

    def _at(self, now: float) -> None:
        self.stream.set_time(TIMELINE, timestamp=now)
        self._time = now

    def _scalar(self, path: str, value: float) -> None:
        if np.isfinite(value):
            self.stream.log(path, self.rr.Scalars(float(value)))

    # Status (1 Hz per robot)
    def status(self, msg: wire.Status, now: float) -> None:
        if msg.source == "edge":
            self._edge_status(msg, now)
            return
        state = self.robot(msg.id)
        self._at(now)
        v, prev = msg.values, state.status
        for key, name in LINK_VALUES.items():
            if key in v:
                self._scalar(robot_path(msg.id, "link", name), v[key])
        if "cpu_process" in v:
            self._scalar(robot_path(msg.id, "perception", "cpu_process"), v["cpu_process"])
        # Rates over at least RATE_WINDOW: two statuses close together (a robot starting or
        # stopping) would turn one scan into a spike
        if prev is not None and msg.stamp - prev.stamp < RATE_WINDOW:
            return
        if prev is not None:
            dt = msg.stamp - prev.stamp
            for key, path in (("acked", ("link", "rate_hz")), ("local_done", ("perception", "local_fps")),
                              ("edge_done", ("perception", "edge_fps"))):
                if key in v and key in prev.values:
                    self._scalar(robot_path(msg.id, *path), max(0.0, v[key] - prev.values[key]) / dt)
        state.status = msg

    def _edge_status(self, msg: wire.Status, now: float) -> None:
        self._at(now)
        for name in sorted(msg.values)[:MAX_EDGE_VALUES]:
            if ID.match(name):  # a value name becomes an entity path part
                self._scalar(f"edges/{msg.id}/{name}", msg.values[name])

    # Scans and their acks
    def ack(self, ack: wire.ScanAck, now: float) -> None:
        state = self.robot(ack.robot)
        self._at(now)
        self._scalar(robot_path(ack.robot, "link", "T_s"), ack.interarrival)
        for name, value in (("proc_ms", ack.proc_time * 1e3), ("queue_ms", ack.queue_time * 1e3),
                            ("map_points", float(ack.map_points))):
            self._scalar(robot_path(ack.robot, "mapping", name), value)
        if ack.status != "ok" or not plausible(ack.pose):
            return
        state.poses[ack.seq] = ack.pose
        while len(state.poses) > self.recent_poses:
            state.poses.popitem(last=False)
        state.track[ack.seq] = ack.pose[:3, 3].copy()
        while len(state.track) > self.max_trajectory:
            state.track.popitem(last=False)
        state.track_dirty = True
        self.stream.log(robot_path(ack.robot, "pose"), self.rr.Points3D(
            ack.pose[:3, 3][None], radii=0.3, colors=[EDGE_COLOR], labels=[ack.robot], show_labels=True))
        if state.pending_scan is not None and state.pending_scan[0] == ack.seq:
            self._log_scan(ack.robot, state, *state.pending_scan)
        self.trajectory(ack.robot, now)

    def scan(self, robot: str, seq: int, points: np.ndarray, now: float) -> None:
        """The latest scan (sensor frame); logged in the world once its pose is known, at most one
        per ``scan_period``."""
        state = self.robot(robot)
        if now - state.scan_logged < self.scan_period:
            return
        self._at(now)
        if seq in state.poses:
            self._log_scan(robot, state, seq, points)
        else:
            state.pending_scan = (seq, points)

    def _log_scan(self, robot: str, state: _Robot, seq: int, points: np.ndarray) -> None:
        pose = state.poses[seq]
        points = points[np.abs(points).max(axis=1) <= MAX_COORD] if len(points) else points
        world = points.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        self.stream.log(robot_path(robot, "scan"), self.rr.Points3D(
            world.astype(np.float32), radii=0.03, colors=[SCAN_COLOR]))
        state.pending_scan = None
        state.scan_logged = self._time

    def trajectory(self, robot: str, now: float, force: bool = False) -> None:
        state = self.robot(robot)
        if not state.track_dirty or (not force and now - state.track_logged < self.trajectory_period):
            return
        self._at(now)
        xyz = decimate(np.array(list(state.track.values()), np.float32).reshape(-1, 3),
                       self.max_track_vertices)
        self.stream.log(robot_path(robot, "trajectory"), self.rr.LineStrips3D([xyz], radii=0.05,
                                                                                colors=[EDGE_COLOR]))
        state.track_logged, state.track_dirty = now, False

    # Map (polled: the whole registered map with the trajectory's poses)
    def map(self, reply: wire.MapReply, now: float) -> None:
        state = self.robot(reply.robot)
        self._at(now)
        pts = decimate(reply.points, self.max_map_points)
        self.stream.log(robot_path(reply.robot, "map"), self.rr.Points3D(pts, radii=0.04,
                                                                          colors=[MAP_COLOR]))
        # The edge's poses are authoritative: they also cover scans acked before the viewer started
        keep = np.array([plausible(p) for p in reply.poses], bool).reshape(-1)
        for seq, pose in zip(reply.seqs[keep].tolist(), reply.poses[keep], strict=True):
            state.track[int(seq)] = pose[:3, 3].copy()
        state.track = OrderedDict(sorted(state.track.items())[-self.max_trajectory:])
        state.track_dirty = True
        self.trajectory(reply.robot, now, force=True)

    # Camera
    def preview(self, p: wire.Preview, now: float) -> None:
        """A frame as the robot saw it, with its person boxes, coloured by where it was detected."""
        if len(p.boxes) != len(p.scores):
            raise ValueError(f"preview {p.seq}: {len(p.boxes)} boxes, {len(p.scores)} scores")
        self.robot(p.robot)
        self._at(now)
        color = EDGE_COLOR if p.side == "edge" else LOCAL_COLOR
        self.stream.log(robot_path(p.robot, "camera"), self.rr.EncodedImage(
            contents=p.jpeg.tobytes(), media_type="image/jpeg"))
        self.stream.log(robot_path(p.robot, "camera", "persons"), self.rr.Boxes2D(
            array=p.boxes, array_format=self.rr.Box2DFormat.XYXY, colors=[color] * len(p.boxes),
            labels=[f"{p.side} {s:.2f}" for s in p.scores.tolist()]))
        self._scalar(robot_path(p.robot, "perception", "on_edge"), 1.0 if p.side == "edge" else 0.0)

    def frame(self, f: wire.Frame, now: float) -> None:
        """A frame sent to the edge: kept until its detections come (``detections``)."""
        f.check_size()
        state = self.robot(f.robot)
        if now - state.frame_logged >= self.frame_period:
            state.pending_frame = f

    def detections(self, d: wire.Detections, now: float) -> None:
        state = self.robot(d.robot)
        self._at(now)
        if d.status == "ok":
            self._scalar(robot_path(d.robot, "perception", "edge_infer_ms"), d.infer_time * 1e3)
        f = state.pending_frame
        if f is None or f.seq != d.seq or d.status != "ok":
            return
        path = robot_path(d.robot, "edge_frame")
        if f.encoding == "jpeg":
            self.stream.log(path, self.rr.EncodedImage(contents=f.data.tobytes(), media_type="image/jpeg"))
        else:
            self.stream.log(path, self.rr.Image(f.data.reshape(f.height, f.width, 3), color_model="BGR"))
        # The answer's boxes are in the camera's pixels; the frame as it travelled may be shrunk
        cam_w, cam_h = f.camera_size()
        boxes = d.boxes * np.array([f.width / cam_w, f.height / cam_h] * 2, np.float32)
        self.stream.log(f"{path}/detections", self.rr.Boxes2D(
            array=boxes, array_format=self.rr.Box2DFormat.XYXY, class_ids=d.classes,
            labels=[f"{c} {s:.2f}" for c, s in zip(d.classes.tolist(), d.scores.tolist(), strict=True)],
            colors=[EDGE_COLOR] * len(d.boxes)))
        state.pending_frame, state.frame_logged = None, now
        if not state.edge_frames:
            state.edge_frames = True
            self.stream.send_blueprint(self.blueprint(), make_active=True, make_default=True)
