"""Typed configuration: defaults, then a YAML file, then ``ZOFFLOAD_*`` environment variables,
then command-line flags; unknown keys are errors. The effective config is written beside results.

Environment variables address nested keys with ``__``: ``ZOFFLOAD_ROBOT__VOXEL=0.03`` or
``ZOFFLOAD_EDGE__MAPPER__MAX_POINTS_PER_VOXEL=10``; values are parsed as YAML scalars/lists.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from zoffload.protocol.keys import DEFAULT_NAMESPACE, check_id
from zoffload.runtime.errors import ConfigError
from zoffload.sources.base import Replay


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ZenohSettings(_Strict):
    """The session flags every zoffload program takes (as the zenoh examples do)."""

    mode: Literal["peer", "client", "router"] = "peer"
    connect: list[str] = Field(default_factory=list)
    listen: list[str] = Field(default_factory=list)
    multicast_scouting: bool = True
    # Off whenever traffic must really cross a (shaped) link: with it on, same-host peers pass
    # large payloads through shared memory and only references cross the TCP connection.
    shared_memory: bool = True
    config_file: str | None = None
    cfg: list[str] = Field(default_factory=list)  # "KEY:VALUE" with VALUE in JSON5

    @field_validator("cfg")
    @classmethod
    def _cfg_pairs(cls, v: list[str]) -> list[str]:
        for item in v:
            if ":" not in item:
                raise ValueError(f"--cfg {item!r} must be KEY:VALUE")
        return v


class MapperSettings(_Strict):
    """KISS-ICP on the edge. ``voxel_size`` None = max(max_range / 100, 2 x robot's voxel_max)."""

    enabled: bool = True  # False: receive and ack only (link checks, stream benchmarks)
    voxel_size: float | None = Field(default=None, gt=0)
    min_range: float = Field(default=0.0, ge=0)
    max_range: float | None = Field(default=None, gt=0)  # None: the sensor's, sent by the robot
    max_points_per_voxel: int = Field(default=20, ge=1)
    deskew: bool = False  # scans carry no per-point timestamps on the wire
    map_resolution: float = Field(default=0.1, gt=0)  # global map: one point per voxel this size
    queue: int = Field(default=2, ge=1)  # scans waiting per robot before the oldest is dropped


class DetectorSettings(_Strict):
    """The edge's object detector. ``enabled`` None = on when the model file can be found."""

    enabled: bool | None = None
    model: Literal["nanodet-m", "picodet-s", "yolox-nano"] = "picodet-s"
    model_path: str | None = None
    model_url: str | None = None  # optional download, checked against the pinned SHA-256
    threads: int = Field(default=0, ge=0)  # onnxruntime intra-op threads; 0 = its default
    queue: int = Field(default=2, ge=1)  # frames waiting per robot before the oldest is dropped
    batch: int = Field(default=4, ge=1)  # frames taken per pass when they queue up


class PerceptionSettings(_Strict):
    """The robot's camera pipeline: where each frame is detected, and the local detector."""

    strategy: str = "dynamic"  # robot | edge | ratio:R | thesis | dynamic
    local_model: Literal["nanodet-m", "picodet-s", "yolox-nano"] = "nanodet-m"
    local_model_path: str | None = None
    local_threads: int = Field(default=1, ge=0)  # onnxruntime threads of the local detector
    fps: float | None = Field(default=None, gt=0)  # None: the source's rate (25 for coco-clips)
    max_frames: int | None = Field(default=None, ge=1)
    encoding: Literal["bgr8", "jpeg"] = "bgr8"
    jpeg_quality: int = Field(default=80, ge=1, le=100)
    cpu_max: float = Field(default=90.0, gt=0)  # the rule's CPU bound (process %, one core = 100)
    bw_max_mbps: float | None = Field(default=None, gt=0)  # the rule's bandwidth bound; None = none
    max_in_flight: int = Field(default=4, ge=0)  # dynamic: its window's upper end (unanswered frames)
    reply_timeout: float = Field(default=0.5, gt=0)  # an edge frame unanswered this long is lost
    fallback_losses: int = Field(default=3, ge=1)  # lost in a row (and a silent edge) → fallback
    probe_period: float = Field(default=0.5, gt=0)  # in fallback: one frame to the edge this often
    resume_after: int = Field(default=3, ge=1)  # consecutive prompt probe replies to resume
    cpu_quota: float | None = Field(default=None, gt=0)  # cores the robot process may use (CFS)

    @field_validator("strategy")
    @classmethod
    def _strategy(cls, v: str) -> str:
        from zoffload.policy.offload import make_strategy

        make_strategy(v)  # ValueError names the accepted forms
        return v


class RobotSettings(_Strict):
    robot_id: str = "robot1"
    namespace: str = DEFAULT_NAMESPACE
    scans: str = "sim"  # "sim", a folder of .bin / .pcd / .ply scans, or "none"
    images: str | None = None  # camera: "coco-clips[:FOLDER]", an image folder or a video file
    replay: Replay = "once"
    rate_hz: float | None = Field(default=None, gt=0)  # None: the source's own rate
    max_scans: int | None = Field(default=None, ge=1)
    sim_seed: int = 0
    voxel: float = Field(default=0.05, ge=0)  # fixed voxel size, rate's start, DQN's fallback; 0 = raw
    # "rate" (ours, the default: sized for the link from the acks), "fixed", "dqn" (the packaged
    # model) or "dqn:PATH". Measured against each other in README "Experiments" / "Ours".
    scale_policy: str = "rate"
    voxel_range: tuple[float, float] = (0.01, 0.07)
    # Scan payload: "f32" floats, or "q16z" (coordinates quantised to quant_fraction x voxel
    # size, 5 mm for raw scans, then Zstandard-compressed; decoded on the edge)
    scan_coding: Literal["f32", "q16z"] = "q16z"
    quant_fraction: float = Field(default=0.1, gt=0, le=0.5)
    ack_timeout: float = Field(default=1.0, gt=0)  # an unanswered scan is lost after this
    # Scans sent but not yet answered before a new one waits its turn (dropped at source, newest
    # kept): like a TCP window, it keeps the link carrying whole scans. 0 = no limit.
    max_in_flight: int = Field(default=3, ge=0)
    status_period: float = Field(default=1.0, gt=0)
    wait_edge: float = Field(default=5.0, ge=0)  # seconds to wait for an edge at start
    out_dir: str | None = None
    perception: PerceptionSettings = Field(default_factory=PerceptionSettings)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)

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
    edge_id: str = "edge1"
    namespace: str = DEFAULT_NAMESPACE
    mapper: MapperSettings = Field(default_factory=MapperSettings)
    detector: DetectorSettings = Field(default_factory=DetectorSettings)
    map_dir: str | None = None  # export every robot's map here on shutdown
    map_format: Literal["ply", "pcd"] = "ply"
    status_period: float = Field(default=1.0, gt=0)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)

    @field_validator("edge_id", "namespace")
    @classmethod
    def _ids(cls, v: str) -> str:
        return check_id(v)


S = TypeVar("S", bound=BaseModel)


def _deep_merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def env_overrides(prefix: str, environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Nested overrides from ``<prefix>KEY__SUBKEY=value`` variables."""
    environ = os.environ if environ is None else environ
    out: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(prefix) or name == prefix:
            continue
        path = name[len(prefix):].lower().split("__")
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
        try:
            node[path[-1]] = yaml.safe_load(raw) if raw != "" else None
        except yaml.YAMLError as exc:
            raise ConfigError(f"environment variable {name}: cannot parse {raw!r}: {exc}") from exc
    return out


def load_settings(
    cls: type[S],
    file: str | Path | None = None,
    flags: Mapping[str, Any] | None = None,
    env_prefix: str | None = None,
    environ: Mapping[str, str] | None = None,
) -> S:
    """Defaults < YAML file < environment < flags, validated; ``ConfigError`` names what is wrong."""
    data: dict[str, Any] = {}
    if file is not None:
        path = Path(file)
        try:
            loaded = yaml.safe_load(path.read_text()) or {}
        except OSError as exc:
            raise ConfigError(f"config file {path}: {exc.strerror}") from exc
        except yaml.YAMLError as exc:
            raise ConfigError(f"config file {path}: not valid YAML: {exc}") from exc
        if not isinstance(loaded, dict):
            raise ConfigError(f"config file {path}: the top level must be a mapping")
        data = loaded
    if env_prefix:
        data = _deep_merge(data, env_overrides(env_prefix, environ))
    if flags:
        data = _deep_merge(data, {k: v for k, v in flags.items() if v is not None})
    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc']) or '(top)'}: {err['msg']}" for err in exc.errors()
        )
        where = f" (from {file})" if file else ""
        raise ConfigError(f"invalid {cls.__name__}{where}: {problems}") from exc


def write_effective(settings: BaseModel, path: Path) -> Path:
    """Write the settings actually used, as YAML, so every result says how it was made."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(settings.model_dump(mode="json"), sort_keys=False))
    return path
