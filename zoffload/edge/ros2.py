"""The edge's ROS 2 output: what the edge computes for each robot, as topics of an rmw_zenoh graph
that ``ros2 topic echo`` and RViz read (no ROS install on the edge).

Inputs (on the edge's own session): ``<ns>/data/*/scan_ack/**`` and ``<ns>/data/*/detections/**`` that
this edge publishes (subscribed session-local), ``<ns>/data/*/scan`` and ``<ns>/data/*/frame`` for
the robots' capture stamps, and each robot's map (``map_source``, or this edge's map queryable
``<ns>/ctrl/<robot>/map/<edge>`` asked every ``map_period``: its own edge only, runtime/maps.py).
Outputs (per robot, ``{robot}`` in names is its id; one ROS node, ``zoffload_edge``):

* ``/{robot}/odom`` nav_msgs/Odometry: the pose of each registered scan (world frame → sensor
  frame), with the velocity from the previous one; stamped with the scan's capture stamp;
* ``/tf`` tf2_msgs/TFMessage: the same transform, so RViz places the robot's frames;
* ``/{robot}/map`` sensor_msgs/PointCloud2: the registered map in the world frame, latched
  (TRANSIENT_LOCAL, depth 1: an RViz started later still gets it);
* ``/{robot}/detections`` vision_msgs/Detection2DArray: the edge detector's boxes in the camera
  frame, stamped with the frame's capture stamp, COCO names as class ids.

Stamps are the robot's wall clock (its capture stamps: ROS time on the robot's machine); an ack
whose scan was not seen is stamped with the edge's clock. Poses are KISS-ICP's: the world frame
is the sensor's pose at the robot's first registered scan.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from zoffload.protocol import wire
from zoffload.protocol.intake import robot_in_key
from zoffload.protocol.keys import Keys, check_id
from zoffload.ros2 import messages
from zoffload.ros2.keys import DEFAULT_QOS, KEEP_LAST, LATCHED, RELIABLE, VOLATILE, Qos
from zoffload.ros2.node import Ros2Node, Ros2Publisher
from zoffload.ros2.pointcloud import cloud_msg
from zoffload.ros2.session import Ros2Link, Ros2SessionError
from zoffload.runtime.config import EdgeSettings
from zoffload.runtime.drops import Drops
from zoffload.runtime.errors import ZenohSessionError
from zoffload.runtime.maps import ask_map
from zoffload.runtime.session import undeclare

log = logging.getLogger("zoffload.edge.ros2")

ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
DETECTIONS = "vision_msgs/msg/Detection2DArray"
TF_QOS = Qos(RELIABLE, VOLATILE, KEEP_LAST, 100)  # tf2_ros' broadcaster profile
STAMPS_KEPT = 4096  # capture stamps of recent scans and frames, all robots together
MAX_ROBOTS = 256  # robots with ROS publishers at once (the edge's admission bounds them first)
COCO_NAMES = (
    "person bicycle car motorcycle airplane bus train truck boat traffic_light fire_hydrant stop_sign "
    "parking_meter bench bird cat dog horse sheep cow elephant bear zebra giraffe backpack umbrella "
    "handbag tie suitcase frisbee skis snowboard sports_ball kite baseball_bat baseball_glove "
    "skateboard surfboard tennis_racket bottle wine_glass cup fork knife spoon bowl banana apple "
    "sandwich orange broccoli carrot hot_dog pizza donut cake chair couch potted_plant bed "
    "dining_table toilet tv laptop mouse remote keyboard cell_phone microwave oven toaster sink "
    "refrigerator book clock vase scissors teddy_bear hair_drier toothbrush").split()
COCO_LABELS = dict(enumerate(COCO_NAMES))


@dataclass(frozen=True)
class Ros2Names:
    """Topic and frame names; ``{robot}`` is replaced by each robot's id."""

    odom_topic: str = "/{robot}/odom"
    map_topic: str = "/{robot}/map"
    detections_topic: str = "/{robot}/detections"
    tf: bool = True
    world_frame: str = "{robot}/odom"
    sensor_frame: str = "{robot}/lidar"
    camera_frame: str = "{robot}/camera"

    def of(self, name: str, robot: str) -> str:
        """A frame's name for ``robot``: its id as it is (tf frame ids are free text)."""
        return name.replace("{robot}", robot)

    def topic(self, name: str, robot: str) -> str:
        """A topic's name for ``robot``: ROS names allow letters, digits and ``_`` only, so the
        ``-`` and ``.`` a zoffload id may hold become ``_``."""
        return name.replace("{robot}", robot.replace("-", "_").replace(".", "_"))


@dataclass
class _RobotTopics:
    robot: str
    odom: Ros2Publisher
    map: Ros2Publisher
    detections: Ros2Publisher
    last_pose: np.ndarray | None = None
    last_stamp: float = float("nan")
    acks: int = 0  # registered scans seen
    mapped_at: int = -1  # ``acks`` when the map was last published
    counters: dict[str, int] = field(default_factory=dict)


class Ros2Service:
    """An edge service (edge/service.py) publishing the edge's results to ROS 2."""

    name = "ros2"

    def __init__(self, keys: Keys, link: Ros2Link, names: Ros2Names = Ros2Names(),
                 share_session: bool = False, map_period: float = 2.0, map_max_points: int = 2_000_000,
                 map_source: Callable[[str], np.ndarray | None] | None = None,
                 edge_id: str = "edge1") -> None:
        self.keys = keys
        self.edge_id = check_id(edge_id, "edge id")  # the edge whose maps it asks for
        self.link = link
        self.names = names
        self.share_session = share_session
        self.map_period = map_period
        self.map_max_points = map_max_points
        self.map_source = map_source
        self.drops = Drops(log)
        self.counts: dict[str, int] = {"odom": 0, "tf": 0, "maps": 0, "detections": 0}
        self.robots: dict[str, _RobotTopics] = {}
        self._stamps: OrderedDict[tuple[str, str, int], float] = OrderedDict()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._session: zenoh.Session | None = None
        self._ros_session: zenoh.Session | None = None
        self._node: Ros2Node | None = None
        self._tf: Ros2Publisher | None = None
        self._subs: list[Any] = []
        self._mapper: threading.Thread | None = None

    # Startup
    def start(self, session: zenoh.Session) -> None:
        from zoffload.ros2.typestore import typestore

        typestore()  # load the message types now, not on the first ack
        self._session = session
        try:
            self._ros_session = session if self.share_session else self.link.open()
        except Ros2SessionError as exc:  # no rmw_zenohd there: the edge's exit code for sessions
            raise ZenohSessionError(str(exc)) from exc
        link = self.link
        self._node = Ros2Node(self._ros_session, link.node, link.namespace, link.domain(),
                              link.keyed_attachment)
        if self.names.tf:
            self._tf = self._node.publisher("/tf", TF, TF_QOS)
        local = zenoh.Locality.SESSION_LOCAL  # this edge's own answers only
        self._subs = [
            session.declare_subscriber(self.keys.answers("scan_ack"), self.drops.guard(self._on_ack, "ack"),
                                       allowed_origin=local),
            session.declare_subscriber(self.keys.answers("detections"),
                                       self.drops.guard(self._on_detections, "detections"),
                                       allowed_origin=local),
            session.declare_subscriber(self.keys.all_scans(), self.drops.guard(self._on_capture, "scan")),
            session.declare_subscriber(self.keys.all_frames(), self.drops.guard(self._on_capture, "frame")),
        ]
        self._mapper = threading.Thread(target=self._map_loop, name="ros2-map", daemon=True)
        self._mapper.start()
        log.info("ROS 2 output on domain %d as node %s (odom %s, map %s, detections %s)",
                 self._node.domain_id, link.node, self.names.odom_topic, self.names.map_topic,
                 self.names.detections_topic)

    # Capture stamps: the robot's clock when its sensor delivered the scan or frame
    def _on_capture(self, sample: zenoh.Sample) -> None:
        # Three fields peeked, the points or pixels stepped over (this runs for every robot's
        # scans and frames, other edges' too); the robot named in the payload must be the key's
        key = str(sample.key_expr)
        kind = self.keys.last_chunk(key)
        if (key_robot := robot_in_key(sample, self.keys, self.drops, kind)) is None:
            return
        msg_type = wire.Scan.TYPE if kind == "scan" else wire.Frame.TYPE
        got = wire.peek_fields(sample.payload.to_bytes(), msg_type, ("robot", "seq", "capture_stamp")) or {}
        robot, seq, stamp = got.get("robot"), got.get("seq"), got.get("capture_stamp")
        # (bool is an int to Python; the stamp in the bounds decode would hold it to)
        if not (isinstance(robot, str) and isinstance(seq, int) and isinstance(stamp, (int, float))
                and not isinstance(seq, bool) and not isinstance(stamp, bool)
                and wire.STAMP.lo <= stamp <= wire.STAMP.hi):
            self.drops.drop("malformed", f"a {kind} on {key[:100]} without robot, seq and capture stamp")
            return
        if robot != key_robot:
            self.drops.drop("foreign", f"{kind}: robot {robot[:40]!r} in the payload, {key_robot!r} in the "
                            "key")
            return
        with self._lock:
            self._stamps[(robot, kind, seq)] = float(stamp)
            while len(self._stamps) > STAMPS_KEPT:
                self._stamps.popitem(last=False)

    def _stamp(self, robot: str, kind: str, seq: int) -> float:
        with self._lock:
            stamp = self._stamps.pop((robot, kind, seq), None)
        return stamp if stamp is not None and stamp > 0 else time.time()

    def _robot(self, robot: str) -> _RobotTopics | None:
        with self._lock:
            topics = self.robots.get(robot)
            if topics is not None or self._node is None:
                return topics
            if len(self.robots) >= MAX_ROBOTS:
                self.drops.drop("robots", f"robot {robot}: {MAX_ROBOTS} robots already published")
                return None
            n, node = self.names, self._node
            topics = _RobotTopics(
                robot,
                odom=node.publisher(n.topic(n.odom_topic, robot), ODOMETRY, DEFAULT_QOS),
                map=node.publisher(n.topic(n.map_topic, robot), POINTCLOUD2, LATCHED,
                                   congestion=zenoh.CongestionControl.BLOCK),  # large, rare: whole
                detections=node.publisher(n.topic(n.detections_topic, robot), DETECTIONS, DEFAULT_QOS))
            self.robots[robot] = topics
            return topics

    # Odometry and /tf from each registered scan
    def _on_ack(self, sample: zenoh.Sample) -> None:
        ack = wire.decode(sample.payload.to_bytes(), expect=wire.ScanAck)
        if ack.status != "ok" or not np.isfinite(ack.pose).all():
            return
        topics = self._robot(ack.robot)
        if topics is None:
            return
        stamp = self._stamp(ack.robot, "scan", ack.seq)
        n = self.names
        world, sensor = n.of(n.world_frame, ack.robot), n.of(n.sensor_frame, ack.robot)
        linear, angular = (messages.velocity(topics.last_pose, ack.pose, stamp - topics.last_stamp)
                           if topics.last_pose is not None else (None, None))
        topics.odom.publish(messages.odometry(ack.pose, stamp, world, sensor, linear, angular))
        if self._tf is not None:
            self._tf.publish(messages.tf_message([messages.transform(ack.pose, stamp, world, sensor)]))
        with self._lock:
            topics.last_pose, topics.last_stamp = ack.pose, stamp
            topics.acks += 1
            self.counts["odom"] += 1
            self.counts["tf"] += self._tf is not None

    def _on_detections(self, sample: zenoh.Sample) -> None:
        det = wire.decode(sample.payload.to_bytes(), expect=wire.Detections)
        if det.status != "ok":
            return
        topics = self._robot(det.robot)
        if topics is None:
            return
        stamp = self._stamp(det.robot, "frame", det.seq)
        topics.detections.publish(messages.detections(
            det.boxes, det.scores, det.classes, stamp, self.names.of(self.names.camera_frame, det.robot),
            COCO_LABELS))
        with self._lock:
            self.counts["detections"] += 1

    # The map, every map_period, for robots with new scans
    def _map_loop(self) -> None:
        while not self._stop.wait(self.map_period):
            with self._lock:
                due = [t for t in self.robots.values() if t.acks != t.mapped_at]
            for topics in due:
                try:
                    self.publish_map(topics.robot)
                except Exception as exc:  # a failed map read must not end the loop
                    self.drops.drop("map", f"robot {topics.robot}: {exc}")

    def publish_map(self, robot: str) -> bool:
        """Publish the robot's current map now; False when it has none (yet)."""
        topics = self._robot(robot)
        if topics is None:
            return False
        with self._lock:
            acks, stamp = topics.acks, topics.last_stamp
        points = self.map_source(robot) if self.map_source is not None else self._query_map(robot)
        if points is None or len(points) == 0:
            return False
        if len(points) > self.map_max_points:  # an even thinning keeps the map's extent
            points = points[:: int(np.ceil(len(points) / self.map_max_points))]
        stamp = stamp if np.isfinite(stamp) else time.time()
        world = self.names.of(self.names.world_frame, robot)
        topics.map.publish(cloud_msg(points, messages.header(stamp, world)))
        with self._lock:
            topics.mapped_at = acks
            self.counts["maps"] += 1
        return True

    def _query_map(self, robot: str) -> np.ndarray | None:
        assert self._session is not None
        reply = ask_map(self._session, self.keys, robot, [self.edge_id], self.drops)
        return reply.points if reply is not None else None

    # Status, eviction, shutdown
    def status(self) -> dict[str, float]:
        with self._lock:
            values = {f"ros2.{k}": float(v) for k, v in self.counts.items()}
        values.update({f"ros2.drop.{k}": float(v) for k, v in self.drops.snapshot().items()})
        return values

    def evict(self, robot: str) -> None:
        with self._lock:
            topics = self.robots.pop(robot, None)
            stale = [k for k in self._stamps if k[0] == robot]
            for k in stale:
                del self._stamps[k]
        if topics is not None:
            for pub in (topics.odom, topics.map, topics.detections):
                pub.close()

    def stop(self) -> None:
        self._stop.set()
        undeclare(*self._subs)
        self._subs = []
        if self._mapper is not None:
            self._mapper.join(timeout=15)
        if self._node is not None:
            self._node.close()
        if self._ros_session is not None and not self.share_session:
            self._ros_session.close()
        self._ros_session = None
        log.info("ROS 2 output stopped: %s", self.counts)


def ros2_service(settings: EdgeSettings, keys: Keys,
                 map_source: Callable[[str], np.ndarray | None] | None = None) -> Ros2Service | None:
    """The ROS 2 output for these edge settings (``EdgeSettings``), None when it is off."""
    r = settings.ros2
    if not r.enabled:
        return None
    names = Ros2Names(odom_topic=r.odom_topic, map_topic=r.map_topic, detections_topic=r.detections_topic,
                      tf=r.tf, world_frame=r.world_frame, sensor_frame=r.sensor_frame,
                      camera_frame=r.camera_frame)
    return Ros2Service(keys, r.link(r.node), names, share_session=r.share_session, map_period=r.map_period,
                       map_max_points=r.map_max_points, map_source=map_source, edge_id=settings.edge_id)
