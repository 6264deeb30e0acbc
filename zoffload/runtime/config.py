"""Typed settings: one pydantic model per concern (the Zenoh session, the mapper, the detector,
the camera pipeline) combined in ``RobotSettings`` and ``EdgeSettings``; unknown keys are errors.

Each setting is declared once, as a field here: its ``description`` is the help text of its
command-line flag (``zoffload.cli.flags`` builds the daemons' flags from these models), and
``runtime/loading.py`` reads them from a YAML file, the environment and flags.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from zoffload.protocol.keys import DEFAULT_NAMESPACE, check_id
from zoffload.sources.base import Replay

if TYPE_CHECKING:
    from zoffload.ros2.session import Ros2Link

DetectorModel = Literal["nanodet-m", "picodet-s", "yolox-nano"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ZenohSettings(_Strict):
    """The session flags every zoffload program takes (as the zenoh examples do)."""

    mode: Literal["peer", "client", "router"] = Field(default="peer", description="Zenoh session mode")
    connect: list[str] = Field(default_factory=list, description="endpoint to connect to")
    listen: list[str] = Field(default_factory=list, description="endpoint to listen on")
    multicast_scouting: bool = Field(default=True, description="discover peers by UDP multicast scouting")
    # With it on, same-host peers pass large payloads through shared memory and only references
    # cross the TCP connection: off whenever traffic must really cross a (shaped) link.
    shared_memory: bool = Field(
        default=True,
        description="exchange payloads with same-host peers in shared memory; off behind the link emulator",
    )
    config_file: str | None = Field(
        default=None, description="Zenoh JSON5 config file, applied before the other session settings"
    )
    cfg: list[str] = Field(
        default_factory=list, description="any Zenoh config key as KEY:VALUE, VALUE in JSON5"
    )
    # TLS (runtime/session.py turns these into transport/link/tls keys; `zoffload certs` makes them)
    tls_ca: str | None = Field(
        default=None, description="CA certificate (PEM) the peer's certificate must chain to: turns on TLS",
    )
    tls_cert: str | None = Field(
        default=None, description="this program's certificate (PEM, common name = its id): mutual TLS",
    )
    tls_key: str | None = Field(default=None, description="the private key (PEM) of tls_cert")
    user: str | None = Field(default=None, description="user name for Zenoh's user/password authentication")
    password_file: str | None = Field(
        default=None, description="file holding that user's password (first line; keep it private)",
    )

    @field_validator("cfg")
    @classmethod
    def _cfg_pairs(cls, v: list[str]) -> list[str]:
        for item in v:
            if ":" not in item:
                raise ValueError(f"--cfg {item!r} must be KEY:VALUE")
        return v


class MapperSettings(_Strict):
    """KISS-ICP on the edge."""

    enabled: bool = Field(
        default=True,
        description="map the scans (off: receive and ack only, for link checks)",
    )
    voxel_size: float | None = Field(
        default=None, gt=0,
        description="KISS-ICP voxel in m; unset: max(max_range / 100, 2 x robot's voxel_max)",
    )
    min_range: float = Field(default=0.0, ge=0, description="ignore points closer than this, in m")
    max_range: float | None = Field(
        default=None, gt=0,
        description="ignore points farther than this, in m; unset: the sensor's, from the robot",
    )
    max_points_per_voxel: int = Field(default=20, ge=1, description="KISS-ICP local map density")
    deskew: bool = Field(
        default=False,
        description="deskew scans (they carry no per-point timestamps on the wire)",
    )
    map_resolution: float = Field(
        default=0.1, gt=0, description="global map: one point per voxel of this size, in m"
    )
    queue: int = Field(
        default=2, ge=1, description="scans waiting per robot before one is dropped (the oldest, spared once "
        "when its neighbour is gone)"
    )
    workers: int | None = Field(
        default=None, ge=1, description="mapping threads serving every robot's queue; unset: one per core",
    )
    processes: int | None = Field(
        default=None, ge=0,
        description="processes the mappers run in (KISS-ICP holds the GIL); unset: one per 2 cores; 0: none",
    )
    register_timeout: float = Field(
        default=5.0, gt=0,
        description="s (and s of CPU) a mapper process may take to register a scan (busy: call_timeout)",
    )
    call_timeout: float = Field(
        default=30.0, gt=0,
        description="s a mapper process may take for other calls (an attach's backfill, a map export)",
    )
    map_budget: int = Field(
        default=2_000_000, ge=1,
        description="global map points kept per robot; beyond it new voxels are counted, not stored",
    )
    trajectory_budget: int = Field(
        default=100_000, ge=1,
        description="poses kept in memory per robot; older ones go to map_dir (or are only counted)",
    )


class AdmissionSettings(_Strict):
    """Which robots the edge serves: others get a refusal, never state on the edge."""

    robots: list[str] = Field(
        default_factory=list, description="the robots served (allowlist); empty: any id, up to max_robots",
    )
    max_robots: int = Field(default=16, ge=1, description="robots served at once")
    idle_timeout: float = Field(
        default=300.0, gt=0,
        description="seconds without a scan or frame before a robot is forgotten (its map exported first)",
    )
    refusals_per_s: float = Field(
        default=20.0, gt=0,
        description="refusals answered per second, all robots together; the rest are counted",
    )

    @field_validator("robots")
    @classmethod
    def _ids(cls, v: list[str]) -> list[str]:
        return [check_id(r, "robot id") for r in v]


class EdgeFleetSettings(_Strict):
    """The edge in a fleet: robots attach to it (and are refused when it is full), it hands each one
    a checkpoint every few scans, and on SIGTERM it drains (final checkpoints, waits until its
    robots have moved to another edge)."""

    capacity: int | None = Field(
        default=None, ge=1,
        description="robots mapped at once; more are refused at attach (default: admission.max_robots)",
    )
    require_attach: bool = Field(
        default=False,
        description="map only robots that attached; off: a robot without the attach protocol "
                    "(epoch 0) is mapped by every edge that hears it",
    )
    checkpoint_every: int = Field(
        default=10, ge=1, description="scans between the checkpoints sent to each robot",
    )
    checkpoint_resolution: float | None = Field(
        default=None, gt=0,
        description="voxel size of a checkpoint's local map, in m (default: half the mapper's voxel size, "
                    "KISS-ICP's own grid for a scan's points, coded; the mapper's voxel size in float32 "
                    "for a robot that reads codec version 5 or older)",
    )
    final_checkpoint_resolution: float = Field(
        default=0.0, ge=0,
        description="voxel size of the local map in the final checkpoint of a drain or shed, in m "
                    "(0: the whole local map, so the next edge continues the pose within ~1 cm)",
    )
    drain_timeout: float = Field(
        default=10.0, ge=0,
        description="seconds a draining edge (SIGTERM) waits for its robots to move before it stops",
    )
    shed: bool = Field(
        default=True,
        description="when the mappers fall behind, hand the newest robot to another edge",
    )
    shed_load: float = Field(
        default=0.9, gt=0, le=1.0,
        description="the mapper workers' busy share over the last few seconds that, with scans dropped, "
        "counts as behind",
    )
    shed_late: float = Field(
        default=0.05, ge=0, le=1.0,
        description="share of the scans of the last few seconds answered later than their robot's period "
        "after they arrived that counts as behind (0.05: the robots kept stay 95 percent on time)",
    )


class LimitsSettings(_Strict):
    """What the edge accepts in one message; checked before anything is allocated."""

    # Peak edge memory for a scan of zeros at the cap (decoding, float64 copies, KISS-ICP), measured
    # by tests/system/test_regressions.py: 500k points +65 MB, 1M +115 MB, 2M +187 MB. 500k keeps
    # any crafted scan within +100 MB and is ~2x a 128-beam sensor's full sweep (262k points)
    max_points: int = Field(default=500_000, ge=1, description="points in one scan")
    max_pixels: int = Field(default=3840 * 2160, ge=1, description="pixels in one camera frame")
    max_bytes: int = Field(default=64 * 1024 * 1024, ge=1024, description="bytes of one message")


class DetectorSettings(_Strict):
    """The edge's object detector."""

    enabled: bool | None = Field(
        default=None,
        description="run the detector; unset: when its model file is found (on: a missing model is fatal)",
    )
    model: DetectorModel = Field(default="picodet-s", description="detector model")
    model_path: str | None = Field(
        default=None, description="the model's ONNX file; unset: searched in the model folders"
    )
    model_url: str | None = Field(
        default=None, description="download the model from here, checked against the pinned SHA-256"
    )
    threads: int = Field(default=0, ge=0, description="onnxruntime intra-op threads; 0 = its default")
    queue: int = Field(default=2, ge=1, description="frames waiting per robot before the oldest is dropped")
    batch: int = Field(default=4, ge=1, description="robots' frames taken per pass when they queue up")
    serve: Literal["newest", "oldest"] = Field(
        default="newest",
        description="a robot's waiting frame a pass takes: newest (older ones answered dropped) or oldest",
    )


class PerceptionSettings(_Strict):
    """The robot's camera pipeline: where each frame is detected, and the local detector."""

    strategy: str = Field(
        default="dispatch",
        description="where each frame is detected: robot, edge, ratio:R, thesis, dynamic or dispatch (ours)",
    )
    local_model: DetectorModel = Field(default="nanodet-m", description="the robot's own detector model")
    local_model_path: str | None = Field(
        default=None, description="the local model's ONNX file; unset: searched in the model folders"
    )
    local_threads: int = Field(default=1, ge=0, description="onnxruntime threads of the local detector")
    fps: float | None = Field(
        default=None, gt=0, description="camera rate; unset: the source's (25 for coco-clips)"
    )
    max_frames: int | None = Field(default=None, ge=1, description="stop the camera after this many frames")
    replay: Replay = Field(
        default="once", description="how a recorded image source is replayed (loop: over and over, a soak)"
    )
    encoding: Literal["bgr8", "jpeg", "auto"] = Field(
        default="auto",
        description="frames to the edge: bgr8 (raw), jpeg, or auto (chosen per frame by the link)",
    )
    jpeg_quality: int = Field(default=80, ge=1, le=100, description="JPEG quality of frames sent as jpeg")
    send_size: Literal["detector", "camera"] = Field(
        default="detector",
        description="frames to the edge shrunk to its detector's input (as it says), or at the camera's size",
    )
    cpu_max: float = Field(
        default=90.0, gt=0, description="the rule's CPU bound: process %, one core = 100 (above it: edge)"
    )
    bw_max_mbps: float | None = Field(
        default=None, gt=0, description="the rule's bandwidth bound in Mbps (above it: robot); unset: none"
    )
    max_in_flight: int = Field(
        default=4, ge=0,
        description="dispatch, dynamic: unanswered edge frames at most (dynamic adapts between 2 and this)",
    )
    max_age: float = Field(
        default=0.6, gt=0,
        description="dispatch: seconds from capture a result is worth the work; later frames are skipped",
    )
    local_bias: float = Field(
        default=0.04, ge=0,
        description="dispatch: seconds sooner the robot must finish a frame to take it (learn_bias: prior)",
    )
    learn_bias: bool = Field(
        default=False,
        description="dispatch: learn local_bias from how well each side agrees with the edge's later answers",
    )
    refresh_period: float = Field(
        default=1.0, gt=0,
        description="dispatch: seconds without an edge frame before a local frame is also copied to the edge",
    )
    retry_period: float = Field(
        default=0.2, gt=0,
        description="dispatch: seconds between frames (or copies) sent to an edge that stopped answering",
    )
    base_period: float = Field(
        default=20.0, gt=0,
        description="dispatch: seconds without a frame sent alone before the edge path is drained for one",
    )
    cpu_share: float = Field(
        default=1.0, gt=0, le=1,
        description="dispatch: share of the CPU quota the robot fills; its local detector is paced within it",
    )
    overflow: bool = Field(
        default=True,
        description="dispatch: a stalling local detector takes, spaced, frames the full edge path cannot",
    )
    preview_period: float = Field(
        default=0.25, ge=0,
        description="seconds between viewer previews at most (only while a viewer subscribes); 0: none",
    )
    reply_timeout: float = Field(
        default=0.5, gt=0, description="seconds before an unanswered edge frame is lost"
    )
    fallback_losses: int = Field(
        default=3, ge=1,
        description="frames lost in a row (with a silent edge) before falling back to the robot",
    )
    probe_period: float = Field(
        default=0.5, gt=0, description="in fallback: seconds between probe frames to the edge"
    )
    resume_after: int = Field(
        default=3, ge=1, description="prompt probe replies in a row to resume offloading"
    )
    cpu_quota: float | None = Field(
        default=None, gt=0, description="cores the robot process may use (CFS quota); unset: no quota"
    )

    @field_validator("strategy")
    @classmethod
    def _strategy(cls, v: str) -> str:
        from zoffload.policy.offload import make_strategy

        make_strategy(v)  # ValueError names the accepted forms
        return v


class Ros2Settings(_Strict):
    """Joining a ROS 2 graph on rmw_zenoh (no ROS install): the ROS side's own Zenoh session."""

    domain_id: int | None = Field(
        default=None, ge=0, le=232, description="ROS domain id; unset: $ROS_DOMAIN_ID, else 0")
    mode: Literal["client", "peer"] = Field(
        default="client", description="ROS-side session mode (a client of the rmw_zenohd router)")
    connect: list[str] = Field(
        default_factory=lambda: ["tcp/localhost:7447"], description="the rmw_zenohd router to connect to")
    listen: list[str] = Field(default_factory=list, description="ROS-side endpoints to listen on")
    config_file: str | None = Field(
        default=None,
        description="Zenoh config file of the ROS side; unset: $ZENOH_SESSION_CONFIG_URI, else the above",
    )
    namespace: str = Field(default="/", description="the ROS namespace of zoffload's node")
    attachment: Literal["plain", "keyed"] = Field(
        default="plain",
        description="attachment format: plain (Jazzy >= 0.2.4, Kilted, Rolling), keyed (Jazzy 0.2.0-0.2.3)",
    )

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, v: str) -> str:
        from zoffload.ros2.keys import namespace_name

        return namespace_name(v)  # ValueError: not a ROS namespace

    def link(self, node: str) -> Ros2Link:
        from zoffload.ros2.session import Ros2Link

        return Ros2Link(domain_id=self.domain_id, mode=self.mode, connect=tuple(self.connect),
                        listen=tuple(self.listen), config_file=self.config_file, node=node,
                        namespace=self.namespace, keyed_attachment=self.attachment == "keyed")


class RobotRos2Settings(Ros2Settings):
    """The robot's ROS 2 inputs (``--scans ros2:/TOPIC``, ``--images ros2:/TOPIC``)."""

    node: str = Field(default="zoffload_robot", description="the node name the robot appears as")

    @field_validator("node")
    @classmethod
    def _node(cls, v: str) -> str:
        from zoffload.ros2.keys import node_name

        return node_name(v)


class EdgeRos2Settings(Ros2Settings):
    """The edge's ROS 2 outputs, per robot: odometry and /tf from each ack, the map (latched),
    detections. ``{robot}`` in a topic or frame is the robot's id."""

    enabled: bool = Field(default=False, description="publish to ROS 2")
    share_session: bool = Field(
        default=False, description="publish on the edge's own Zenoh session instead of a ROS-side one")
    node: str = Field(default="zoffload_edge", description="the node name the edge appears as")
    odom_topic: str = Field(default="/{robot}/odom", description="nav_msgs/Odometry topic")
    tf: bool = Field(default=True, description="broadcast world frame -> sensor frame on /tf")
    map_topic: str = Field(default="/{robot}/map", description="sensor_msgs/PointCloud2 map topic (latched)")
    detections_topic: str = Field(
        default="/{robot}/detections", description="vision_msgs/Detection2DArray topic")
    world_frame: str = Field(default="{robot}/odom", description="frame of poses and the map")
    sensor_frame: str = Field(default="{robot}/lidar", description="the LiDAR's frame (the odometry's child)")
    camera_frame: str = Field(default="{robot}/camera", description="frame of the detections")
    map_period: float = Field(default=2.0, gt=0, description="seconds between map publications")
    map_max_points: int = Field(default=2_000_000, ge=1, description="points of a published map at most")

    @field_validator("odom_topic", "map_topic", "detections_topic")
    @classmethod
    def _topic(cls, v: str) -> str:
        from zoffload.ros2.keys import topic_name

        topic_name(v.replace("{robot}", "robot"))  # ValueError names what ROS would refuse
        return v

    @field_validator("node")
    @classmethod
    def _node(cls, v: str) -> str:
        from zoffload.ros2.keys import node_name

        return node_name(v)


class RobotFleetSettings(_Strict):
    """How the robot picks its edge and keeps its pose: it attaches to one live edge (weighted
    rendezvous ranking), moves to another when that edge goes, drains, refuses it or stops
    answering, and registers scans itself with a light KISS-ICP while no edge maps it."""

    attach: bool = Field(
        default=True,
        description="use the attach protocol; off: stream to whatever edge listens (no failover)",
    )
    attach_timeout: float = Field(default=1.0, gt=0, description="seconds an edge has to answer an attach")
    failover_after: float = Field(
        default=1.0, gt=0,
        description="seconds without any ack from the robot's edge (scans in flight) before it moves, "
                    "when another live edge could take it (else it stays up to 5x longer, bridging)",
    )
    local_odometry: bool = Field(
        default=True, description="register scans on the robot while no edge maps it",
    )
    local_voxel: float | None = Field(
        default=None, gt=0,
        description="voxel size of the local odometry, in m (default: max_range / 50, coarse and cheap)",
    )
    local_threads: int = Field(default=1, ge=1, description="threads of the local odometry's KISS-ICP")
    catch_up: int = Field(
        default=20, ge=0,
        description="scans sent since the newest answered one that the robot holds (by reference), spread "
                    "over them when there are more, so the local odometry can register the ones its edge "
                    "never answered",
    )
    backfill_scans: int = Field(
        default=50, ge=0, le=64,
        description="scans the robot registered itself while no edge mapped it that it keeps, at "
                    "backfill_voxel, with their poses, for the next attach to hand over (0: none; when "
                    "full, every other one is dropped but the outage's first and the newest, so they "
                    "span the whole outage): the edge that mapped it registers them instead of jumping the "
                    "outage (codec versions 9 and 10)",
    )
    backfill_voxel: float | None = Field(
        default=None, gt=0, le=10,
        description="the grid those scans are kept and sent at where the link has room, in m (default: "
                    "a quarter of the local odometry's voxel, at most 10); where it has less, an attach "
                    "sends them at twice the grid, and so on up to the local odometry's voxel",
    )
    backfill_bytes: int = Field(
        default=131_072, ge=0,
        description="bytes of backfill an attach may carry on any link (coded scans; at the odometry's "
                    "voxel thinned evenly beyond; an attach that goes unanswered with a larger one is "
                    "sent again with one of this size, one that goes unanswered with this size without; "
                    "0: no backfill)",
    )
    backfill_bytes_max: int = Field(
        default=1_048_576, ge=0,
        description="bytes of backfill an attach may carry on a link seen to carry them, with the rest "
                    "of the attach, in half the attach_timeout (the most bytes an acked scan carried per "
                    "second of its round trip less the edge's queue and registration)",
    )
    bridge_after: float | None = Field(
        default=None, gt=0,
        description="seconds an edge may be late with its acks before the robot also registers its "
                    "scans itself (default: 2 scan periods or 2 round trips, at most failover_after / 2)",
    )


class RobotSettings(_Strict):
    """The robot daemon: a scan source, its voxel sizing, the link to the edge and the camera."""

    robot_id: str = Field(default="robot1", description="this robot's id (one key chunk)")
    namespace: str = Field(default=DEFAULT_NAMESPACE, description="key namespace, the same on robot and edge")
    scans: str = Field(
        default="sim",
        description="scans: sim[:speed=M/S,sweep], a .bin/.pcd/.ply folder, ros2:/TOPIC, "
        "bag:PATH[:/TOPIC], none",
    )
    images: str | None = Field(
        default=None,
        description="camera: coco-clips[:FOLDER], image folder, video, ros2:/TOPIC, "
        "bag:PATH[:/TOPIC]; unset: none",
    )
    replay: Replay = Field(
        default="once", description="how a recorded source is replayed (pingpong: forward then back)"
    )
    rate_hz: float | None = Field(
        default=None, gt=0, description="sensor rate in Hz; unset: the source's own rate"
    )
    max_scans: int | None = Field(default=None, ge=1, description="stop after this many scans")
    sim_seed: int = Field(default=0, description="simulator scene seed")
    bin_fields: str | None = Field(
        default=None,
        description="columns of .bin scans (x,y,z,i,t or x,y,z,i,t:u4:ns); "
        "unset: KITTI, .pcd.bin nuScenes",
    )
    ros2: RobotRos2Settings = Field(
        default_factory=RobotRos2Settings, description="ROS 2 inputs (scans/images ros2:/TOPIC)")
    voxel: float = Field(
        default=0.05, ge=0,
        description="voxel size in m: the fixed policy's, the rate policy's start, the DQN fallback; 0 = raw",
    )
    # Measured against each other in README "Experiments" / "Ours".
    scale_policy: str = Field(
        default="rate",
        description="voxel sizing: rate (ours, sized for the link from the acks), fixed, dqn, dqn:PATH",
    )
    voxel_range: tuple[float, float] = Field(
        default=(0.01, 0.07), description="the scale policy's voxel range in m (0.02 0.5 for an HDL-64)"
    )
    scan_coding: Literal["f32", "q16z", "q16d"] = Field(
        default="q16d",
        description="scan payload: f32 floats, q16z or q16d (quantised; q16d compressed when needed)",
    )
    quant_fraction: float = Field(
        default=0.1, gt=0, le=0.5, description="q16 step as a fraction of the voxel size (raw scans: 5 mm)"
    )
    zstd_level: int = Field(default=1, ge=-7, le=22, description="q16d's Zstandard level")
    # The rate policy when nothing in voxel_range fits the link (docs/scan-policy-log.md, "Unseen links")
    voxel_widen: float = Field(
        default=2.0, ge=1.0,
        description="rate policy: widen voxel_range up to this times its end when nothing fits; 1 = never",
    )
    max_skip: int = Field(
        default=2, ge=0,
        description="rate policy: scans it may skip in a row when even the widened range does not fit",
    )
    stall_after: float = Field(
        default=0.5, ge=0,
        description="rate policy: seconds without an ack (scans in flight) before it skips; 0 = never",
    )
    jitter_pace: int = Field(
        default=1, ge=1,
        description="rate policy: periods per scan it may take to absorb the link's jitter; 1 = never",
    )
    ack_timeout: float = Field(default=1.0, gt=0, description="seconds before an unanswered scan is lost")
    ack_timeout_max: float | None = Field(
        default=4.0, gt=0,
        description="the ack timeout follows the round trip (TCP's) from ack_timeout up to this; null: fixed",
    )
    # Like a TCP window, the limit keeps the link carrying whole scans: the excess is dropped at
    # the source, newest kept.
    max_in_flight: int = Field(
        default=3, ge=0, description="unanswered scans before the next is held back; 0 = no limit"
    )
    # A scan the edge is queueing or registering is unanswered but off the link: the window
    # widens by the edge's time per scan (the median of the last 20 acks) in periods, at most
    # doubling
    window_edge_time: bool = Field(
        default=True, description="widen the window of unanswered scans by the edge's time per scan"
    )
    # A long path (250 ms each way) holds 6-7 scans at 10 Hz with no queue on it: the window is
    # at least the path's round trip (the route's quickest, or the floor of the last 10 s where that
    # is higher) in periods, rounded up, plus one (at most 8 x base)
    window_path: bool = Field(
        default=True, description="widen the window of unanswered scans to the path's quickest round trip"
    )
    # A scan the window holds back waits for a slot until the next scan is due (a period) and goes
    # when an ack frees one; else (or off) it is dropped at the source, unannounced
    window_hold: bool = Field(
        default=True, description="a scan the full window holds back waits up to a period for a free slot"
    )
    status_period: float = Field(default=1.0, gt=0, description="seconds between status messages")
    heap_trim_period: float = Field(
        default=60.0, ge=0,
        description="seconds between returns of the allocator's free memory to the system (0: never)",
    )
    wait_edge: float = Field(
        default=5.0, ge=0, description="seconds to wait for an edge at start (it runs on without one)"
    )
    out_dir: str | None = Field(
        default=None,
        description="results folder (config, metrics, per-scan CSV, poses)",
    )
    perception: PerceptionSettings = Field(
        default_factory=PerceptionSettings, description="the camera pipeline"
    )
    fleet: RobotFleetSettings = Field(
        default_factory=RobotFleetSettings, description="edge assignment, failover, local odometry",
    )
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="the Zenoh session")

    @field_validator("robot_id", "namespace")
    @classmethod
    def _ids(cls, v: str) -> str:
        return check_id(v)

    @field_validator("voxel_range")
    @classmethod
    def _range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not 0 < v[0] <= v[1]:
            raise ValueError("voxel_range must be [low, high] with 0 < low <= high")
        return v

    @field_validator("scale_policy")
    @classmethod
    def _scale_policy(cls, v: str) -> str:
        if v not in ("rate", "fixed", "dqn") and not (v.startswith("dqn:") and len(v) > 4):
            raise ValueError(f"unknown scale policy {v!r} (rate, fixed, dqn, dqn:PATH)")
        return v


class EdgeSettings(_Strict):
    """The edge daemon: maps each robot's scans and serves its detector."""

    edge_id: str = Field(default="edge1", description="this edge's id (one key chunk)")
    namespace: str = Field(default=DEFAULT_NAMESPACE, description="key namespace, the same on robot and edge")
    mapper: MapperSettings = Field(default_factory=MapperSettings, description="KISS-ICP mapping")
    detector: DetectorSettings = Field(default_factory=DetectorSettings, description="the object detector")
    admission: AdmissionSettings = Field(default_factory=AdmissionSettings, description="robots served")
    limits: LimitsSettings = Field(default_factory=LimitsSettings, description="message size caps")
    fleet: EdgeFleetSettings = Field(
        default_factory=EdgeFleetSettings, description="attach, checkpoints, drain, shedding",
    )
    ros2: EdgeRos2Settings = Field(default_factory=EdgeRos2Settings, description="ROS 2 outputs")
    map_dir: str | None = Field(
        default=None, description="export every robot's map and trajectory here on shutdown"
    )
    map_format: Literal["ply", "pcd"] = Field(default="ply", description="file format of the exported maps")
    status_period: float = Field(default=1.0, gt=0, description="seconds between status messages")
    heap_trim_period: float = Field(
        default=60.0, ge=0,
        description="seconds between returns of the allocator's free memory to the system (0: never)",
    )
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="the Zenoh session")

    @field_validator("edge_id", "namespace")
    @classmethod
    def _ids(cls, v: str) -> str:
        return check_id(v)
