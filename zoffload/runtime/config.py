"""Typed settings: one pydantic model per concern (the Zenoh session, the mapper, the detector,
the camera pipeline) combined in ``RobotSettings`` and ``EdgeSettings``; unknown keys are errors.

Each setting is declared once, as a field here: its ``description`` is the help text of its
command-line flag (``zoffload.cli.flags`` builds the daemons' flags from these models), and
``runtime/loading.py`` reads them from a YAML file, the environment and flags.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from zoffload.protocol.keys import DEFAULT_NAMESPACE, check_id
from zoffload.sources.base import Replay

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
    queue: int = Field(default=2, ge=1, description="scans waiting per robot before the oldest is dropped")


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
    batch: int = Field(default=4, ge=1, description="frames taken per pass when they queue up")


class PerceptionSettings(_Strict):
    """The robot's camera pipeline: where each frame is detected, and the local detector."""

    strategy: str = Field(
        default="dynamic",
        description="where each frame is detected: robot, edge, ratio:R, thesis or dynamic (ours)",
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
    encoding: Literal["bgr8", "jpeg"] = Field(
        default="bgr8",
        description="frames to the edge raw (bgr8) or as JPEG",
    )
    jpeg_quality: int = Field(default=80, ge=1, le=100, description="JPEG quality of frames sent as jpeg")
    cpu_max: float = Field(
        default=90.0, gt=0, description="the rule's CPU bound: process %, one core = 100 (above it: edge)"
    )
    bw_max_mbps: float | None = Field(
        default=None, gt=0, description="the rule's bandwidth bound in Mbps (above it: robot); unset: none"
    )
    max_in_flight: int = Field(
        default=4, ge=0,
        description="dynamic: its window's upper end of unanswered frames",
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


class RobotSettings(_Strict):
    """The robot daemon: a scan source, its voxel sizing, the link to the edge and the camera."""

    robot_id: str = Field(default="robot1", description="this robot's id (one key chunk)")
    namespace: str = Field(default=DEFAULT_NAMESPACE, description="key namespace, the same on robot and edge")
    scans: str = Field(
        default="sim",
        description="scan source: sim, a folder of .bin/.pcd/.ply scans, or none",
    )
    images: str | None = Field(
        default=None,
        description="camera: coco-clips[:FOLDER], an image folder or a video file; unset: no camera",
    )
    replay: Replay = Field(
        default="once", description="how a recorded source is replayed (pingpong: forward then back)"
    )
    rate_hz: float | None = Field(
        default=None, gt=0, description="sensor rate in Hz; unset: the source's own rate"
    )
    max_scans: int | None = Field(default=None, ge=1, description="stop after this many scans")
    sim_seed: int = Field(default=0, description="simulator scene seed")
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
    scan_coding: Literal["f32", "q16z"] = Field(
        default="q16z",
        description="scan payload: f32 floats, or q16z (quantised, Zstandard; decoded on the edge)",
    )
    quant_fraction: float = Field(
        default=0.1, gt=0, le=0.5, description="q16z step as a fraction of the voxel size (raw scans: 5 mm)"
    )
    ack_timeout: float = Field(default=1.0, gt=0, description="seconds before an unanswered scan is lost")
    # Like a TCP window, the limit keeps the link carrying whole scans: the excess is dropped at
    # the source, newest kept.
    max_in_flight: int = Field(
        default=3, ge=0, description="unanswered scans before the next is held back; 0 = no limit"
    )
    status_period: float = Field(default=1.0, gt=0, description="seconds between status messages")
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


class EdgeSettings(_Strict):
    """The edge daemon: maps each robot's scans and serves its detector."""

    edge_id: str = Field(default="edge1", description="this edge's id (one key chunk)")
    namespace: str = Field(default=DEFAULT_NAMESPACE, description="key namespace, the same on robot and edge")
    mapper: MapperSettings = Field(default_factory=MapperSettings, description="KISS-ICP mapping")
    detector: DetectorSettings = Field(default_factory=DetectorSettings, description="the object detector")
    map_dir: str | None = Field(
        default=None, description="export every robot's map and trajectory here on shutdown"
    )
    map_format: Literal["ply", "pcd"] = Field(default="ply", description="file format of the exported maps")
    status_period: float = Field(default=1.0, gt=0, description="seconds between status messages")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="the Zenoh session")

    @field_validator("edge_id", "namespace")
    @classmethod
    def _ids(cls, v: str) -> str:
        return check_id(v)
