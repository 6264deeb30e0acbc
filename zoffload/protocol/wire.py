"""Message types and the msgpack codec every zoffload process speaks.

Each message is one msgpack map: ``v`` (codec version), ``t`` (message type) and the message's
fields. Scalars stay scalars; numpy arrays travel as a map ``{"nd": dtype, "shape": [...],
"data": raw bytes}`` so a 100k-point scan costs one memory copy, not a per-element encoding.

The network is hostile: ``decode`` raises ``WireError`` and nothing else for any bytes, and checks
every field before anything is sized from it — version, type, missing or extra fields, scalar
types, finite floats within each field's range (NaN only where a field means "not measured"),
sequence numbers below 2^63, ids that are key chunks of at most 64 characters, array dtypes,
shapes and byte lengths, and row counts within ``Limits`` (points per scan, pixels per frame,
detections per frame). Decoders of nested payloads (q16z scans, JPEG frames) check the sizes the
message declares before they allocate.

Versions: this build reads 1 to 11. Version 2 only added fields with defaults (the assignment
epoch and edge, deliberately skipped scans, per-point times) and messages (checkpoint, attach,
attach reply), so a version-1 sender is still understood. Version 3 added a frame's camera size
(a frame shrunk to the edge detector's input). Version 4 added the codec version a frame's sender
reads (``Frame.reads``) and, in the answer to a frame whose sender reads 4, the edge's clock when
the frame arrived (``Detections.arrival``: the robot times the link by it, robot/frames.py).
Version 5 added a scan's prior (``Scan.prior``: the robot's own pose estimate while it bridged an
overdue edge), which the robot sends only to an edge whose status says it reads 5. Version 6
added a checkpoint's local map coded as a scan's q16d payload (``Checkpoint.packed``: a tenth of
the size of float32, so a finer map for the same link) and the codec version an attaching robot
reads (``Attach.reads``); the robot says 6 and sends a coded checkpoint only to an edge whose
status says it reads 6, and an edge codes the checkpoints it sends a robot only when that
robot's attach said 6 (``Checkpoint.plain`` turns a coded one back into float32). Version 7 added
the answering edge of a map reply (``MapReply.edge``), sent only on the per-edge map key
(``keys.map``), which only a querier that reads 7 asks (an older one asks the key before it).
Version 8 added a checkpoint's turn rate (``Checkpoint.turn_rate``: the robot's fastest yaw per
scan period the mapper saw, which the next mapper's turned guesses after a gap start from); an
edge puts it in the checkpoints for a robot whose attach said 8, and the robot in the checkpoint
it hands to an edge whose status says 8. Version 9 added an attach's backfill (``Attach.backfill``)
and version 10 the robot's pose of each backfilled scan (``Attach.backfill_poses``). Version 11
added the frame of a scan's prior (``Scan.prior_frame``: the attach's handed-over poses, or the
edge's answers), which the robot says only to an edge whose status says 11; to an older edge it
sends no prior of the scans it read while an attach was under way (the edge could not tell that
frame from its own). A
message is sent as the lowest version that carries its fields away from their defaults, else as
version 2 without them, and each side sends a newer field only to a peer that said it reads it:
the robot shrinks a frame, or says it reads 4, only for an edge whose status said what its
detector takes, or that it reads 4 (``wire.reads``); the edge stamps the arrival only in the
answer to a frame that said so. So a version-2 or -3 robot or edge on the other side reads
everything this one sends it (a passive listener of an older build, such as its viewer, refuses
the newer messages, as it refused shrunk frames: counted and logged there). Decoding is lenient
about the label: a message is read by its fields (each checked), whatever version between 1 and 11
it says it is.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar, cast, overload

import msgpack
import numpy as np

BASE_VERSION = 2  # what a message without newer fields goes as (``encode``: the lowest that carries it)
READS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11)
READS_KEY = "wire.reads"  # the status value where a peer says the newest version it reads
SEQ_MAX = 2**63 - 1
ID_MAX = 64
RIGID_TOL = 1e-6  # a pose's rotation may be this far from orthonormal (float noise; consumers re-project)
ORIGIN_MAX = 1e6  # metres: a q16z scan's corner (its extent is at most 65,535 steps of 1 m)
_ID = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class WireError(ValueError):
    """A payload that is not a valid zoffload message of the expected kind."""


@dataclass(frozen=True)
class Limits:
    """What a receiver accepts at most; every cap is checked before anything is allocated."""

    max_points: int = 4_000_000  # points in one scan (an HDL-64 sweep is ~120k, a 128-beam ~260k)
    max_pixels: int = 7680 * 4320  # pixels of one camera frame (8K)
    max_detections: int = 10_000  # boxes in one detections message
    max_map_points: int = 100_000_000  # points in a map reply or checkpoint
    # points a checkpoint's coded local map may declare (KISS-ICP's local map at half its voxel:
    # ~0.05-0.2M); a declared count is also at most CODED_POINTS_PER_BYTE a byte of its payload,
    # so a kilobyte of compressed zeros cannot make a receiver allocate gigabytes
    max_checkpoint_points: int = 2_000_000
    max_backfill_scans: int = 64  # scans an attach's backfill may carry (the robot sends at most 50)
    max_status_values: int = 1024  # entries of a status message
    max_bytes: int = 512 * 1024 * 1024  # one encoded message


DEFAULT_LIMITS = Limits()
# A q16d point is 6 bytes before Zstandard; real local maps compress 2-10x (0.6 points a byte on
# noisy ground), a perfectly flat synthetic grid 260x (43). A declared count beyond this many points
# a byte of payload is a decompression bomb, not a map.
CODED_POINTS_PER_BYTE = 128


@dataclass(frozen=True)
class ArraySpec:
    """What an array field may hold: one dtype, a shape with ``-1`` for free dimensions, whether
    float values must be finite (``"finite"``, ``"nan-or-finite"``: all NaN means "none"), or
    rigid motions (``"rigid"``, ``"nan-or-rigid"``: finite 4x4 matrices whose rotation is
    orthonormal within ``RIGID_TOL`` and whose last row is 0 0 0 1) and which ``Limits`` cap bounds
    its first dimension."""

    dtype: str
    shape: tuple[int, ...]
    values: str = "finite"
    cap: str | None = None

    def check(self, name: str, arr: np.ndarray) -> np.ndarray:
        if arr.dtype != np.dtype(self.dtype):
            raise WireError(f"field {name!r}: dtype {arr.dtype} where {self.dtype} is expected")
        if arr.ndim != len(self.shape) or any(
            want not in (-1, got) for want, got in zip(self.shape, arr.shape, strict=True)
        ):
            raise WireError(f"field {name!r}: shape {arr.shape} does not fit {self.shape}")
        return arr

    def check_values(self, name: str, arr: np.ndarray) -> None:
        if arr.dtype.kind != "f" or self.values == "any" or arr.size == 0:
            return
        # A finite sum proves every value finite (NaN and inf propagate): one reduction for the
        # common clean array
        if not np.isfinite(np.add.reduce(arr, axis=None, dtype=np.float64)):
            if self.values.startswith("nan-or-") and np.isnan(arr).all():
                return
            if not np.isfinite(arr).all():
                raise WireError(f"field {name!r}: non-finite values")
        if self.values.endswith("rigid"):
            off = rigid_error(arr)
            if not off <= RIGID_TOL:
                raise WireError(f"field {name!r}: not a rigid motion (off by {off:.3g})")


def rigid_error(arr: np.ndarray) -> float:
    """How far (n, 4, 4) or (4, 4) finite matrices are from rigid motions: the largest deviation
    of R Rᵀ from the identity, of det R from 1, or of the last row from 0 0 0 1."""
    m = np.asarray(arr, np.float64).reshape(-1, 4, 4)
    if len(m) == 0:
        return 0.0
    r = m[:, :3, :3]
    gram = np.einsum("nij,nkj->nik", r, r) - np.eye(3)
    bottom = m[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])
    return float(max(np.abs(gram).max(), np.abs(np.linalg.det(r) - 1).max(), np.abs(bottom).max()))


@dataclass(frozen=True)
class Num:
    """Bounds of a number field; ``nan`` allows NaN for "not measured" (inf never)."""

    lo: float = -math.inf
    hi: float = math.inf
    nan: bool = False


def _array(spec: ArraySpec, optional: bool = False, since: int = 1) -> Any:
    """An array field; an ``optional`` one may be absent on the wire (then it is None), and is
    left out while None; one added in a codec version above 2 (``since``) must be optional."""
    assert since <= 2 or optional, "a field newer than version 2 must be optional"
    return field(default=None, metadata={"array": spec, "optional": optional, "since": since})


def _num(default: Any = dataclasses.MISSING, lo: float = -math.inf, hi: float = math.inf,
         nan: bool = False, bounds: Num | None = None, since: int = 1) -> Any:
    """A number field; one added in a codec version above 2 (``since``) is left out of a message
    where it holds its default, so the message still goes as version 2."""
    return field(default=default, metadata={"num": bounds or Num(lo, hi, nan), "since": since})


def _text(default: Any = dataclasses.MISSING, choices: tuple[str, ...] | None = None, max_len: int = 1000,
          ident: bool = False, since: int = 1) -> Any:
    """A text field; one added in a codec version above 2 (``since``) is left out at its default, as
    ``_num``'s."""
    return field(default=default, metadata={"choices": choices, "max_len": max_len, "ident": ident,
                                            "since": since})


SEQ = Num(0, SEQ_MAX)
NAN = float("nan")
STAMP = Num(-1e12, 1e12)  # seconds of some clock: wall or monotonic, never absurd
DURATION = Num(0.0, 3600.0, nan=True)  # a measured duration, NaN when not measured


class Message:
    """Base of all messages: a frozen dataclass with a ``TYPE`` tag."""

    TYPE: ClassVar[str] = ""


@dataclass(frozen=True)
class Scan(Message):
    """One downsampled LiDAR scan, robot → edge."""

    TYPE: ClassVar[str] = "scan"
    robot: str = _text(ident=True)
    seq: int = _num(bounds=SEQ)  # the sensor's scan number: gaps are scans not sent or lost
    send_stamp: float = _num(bounds=STAMP)  # robot clock (time.monotonic()), echoed back in the ack
    capture_stamp: float = _num(bounds=STAMP)  # robot wall clock when the scan was complete
    voxel: float = _num(lo=0.0, hi=10.0)  # voxel size used for this scan [m]; 0 = not downsampled
    voxel_max: float = _num(lo=0.0, hi=10.0)  # upper end of the robot's voxel range: sizes the mapper
    max_range: float = _num(lo=0.1, hi=10_000.0)  # the sensor's range limit [m]: sizes the mapper
    n_raw: int = _num(lo=0, hi=1e9)  # points before downsampling
    points: np.ndarray = _array(ArraySpec("<f4", (-1, 3), cap="max_points"))  # "f32"; empty for "q16z"
    coding: str = _text("f32", choices=("f32", "q16z", "q16d"))  # coding.py: quantised (+ Zstandard)
    quant_step: float = _num(0.0, lo=0.0, hi=1.0)
    n_points: int = _num(-1, lo=-1, hi=1e9)  # points in ``packed`` (q16z), checked against max_points
    origin: np.ndarray | None = _array(ArraySpec("<f8", (3,)), optional=True)
    packed: np.ndarray | None = _array(ArraySpec("|u1", (-1,)), optional=True)
    # Version 2
    epoch: int = _num(0, bounds=SEQ)  # the robot's assignment epoch: an answer from an older one is stale
    skipped: int = _num(0, lo=0, hi=1e6)  # scans deliberately not sent just before this one
    time_span: float = _num(0.0, lo=0.0, hi=10.0)  # seconds the points' times cover; 0 = no times
    times: np.ndarray | None = _array(ArraySpec("<u2", (-1,), cap="max_points"), optional=True)  # f32
    edge: str = _text("", max_len=ID_MAX)  # the edge the robot is attached to ("": no attach protocol)
    # Version 5: the robot's own estimate while its edge's answers were overdue, or for the scans
    # it read while its attach was under way (robot/localpose.py): its local odometry's pose after
    # scan ``prior_seq`` (in the frame of the poses the robot has: the edge's answers, or those of
    # its attach, which the edge moves it as it moved those) and its motion per scan period then.
    # An edge that missed the scans before this one predicts from it instead of stretching its
    # constant-velocity model over the gap (mapping/mapper.py ``predict_from``).
    prior_seq: int = _num(-1, lo=-1, hi=SEQ_MAX, since=5)
    prior: np.ndarray | None = _array(ArraySpec("<f8", (2, 4, 4), values="rigid"), optional=True, since=5)
    # Version 11: the frame the prior is in, as the robot knows it: 1 that of the poses it handed
    # over with its attach to this edge (its local odometry began from its own checkpoint or
    # another edge's: the edge moves it as it moved those), 0 that of this edge's answers (began
    # from this edge's checkpoint under the scan's epoch); -1 not said (an older robot, or one whose
    # odometry began from a checkpoint and a pose in different frames)
    prior_frame: int = _num(-1, lo=-1, hi=1, since=11)

    def __post_init__(self) -> None:
        if (self.prior is None) != (self.prior_seq < 0):
            raise WireError("scan: a prior needs both its scan number and its pose and motion")
        if self.prior_frame >= 0 and self.prior is None:
            raise WireError(f"scan {self.seq}: the frame of a prior it does not carry")
        if self.prior_seq > self.seq:
            raise WireError(f"scan {self.seq}: a prior from a later scan ({self.prior_seq})")

    def cloud(self, limits: Limits = DEFAULT_LIMITS) -> np.ndarray:
        """The scan's points as float32 (n, 3), decoded if coded; ``WireError`` if it cannot be."""
        return self.cloud_and_times(limits)[0]

    def cloud_and_times(self, limits: Limits = DEFAULT_LIMITS) -> tuple[np.ndarray, np.ndarray | None]:
        """Points (n, 3) float32 and, when the scan carries them, per-point times in seconds from
        the scan's first point (n,) float64; ``WireError`` if the payload does not decode."""
        from zoffload.protocol.coding import DECODERS, CodingError, times_from_u16

        if self.coding == "f32":
            pts, q = self.points, self.times
        else:  # q16z, q16d
            if self.packed is None or self.origin is None or self.quant_step <= 0 or self.n_points < 0:
                raise WireError("q16z scan without packed data, origin, step or point count")
            if self.n_points > limits.max_points:
                raise WireError(f"q16z scan of {self.n_points} points (at most {limits.max_points})")
            if not np.all(np.abs(self.origin) <= ORIGIN_MAX):
                raise WireError(f"q16z scan origin {self.origin.tolist()} beyond {ORIGIN_MAX:g} m")
            try:
                pts, q = DECODERS[self.coding](self.packed, self.n_points, self.origin, self.quant_step,
                                               with_times=self.time_span > 0)
            except CodingError as exc:
                raise WireError(str(exc)) from exc
        if self.time_span <= 0:
            return pts, None
        if q is None or len(q) != len(pts):
            raise WireError(f"scan with a time span but {0 if q is None else len(q)} times for "
                            f"{len(pts)} points")
        return pts, times_from_u16(q, self.time_span)


@dataclass(frozen=True)
class ScanAck(Message):
    """The edge's answer to one scan. Durations are on the edge clock; stamps are echoed."""

    TYPE: ClassVar[str] = "scan_ack"
    robot: str = _text(ident=True)
    seq: int = _num(bounds=SEQ)
    send_stamp: float = _num(bounds=STAMP)  # echo of Scan.send_stamp (robot clock)
    # "ok" | "dropped" (edge overloaded) | "error" (registration failed) | "refused" (not admitted)
    status: str = _text(choices=("ok", "dropped", "error", "refused"))
    interarrival: float = _num(bounds=DURATION)  # T: edge clock since the robot's previous scan; NaN first
    queue_time: float = _num(bounds=DURATION)  # waiting on the edge before registration [s]
    proc_time: float = _num(bounds=DURATION)  # registration time [s]: KISS-ICP plus the global-map update
    icp_time: float = _num(bounds=DURATION)  # of which KISS-ICP itself [s]
    map_points: int = _num(lo=0, hi=1e12)
    keypoints: int = _num(lo=0, hi=1e9)  # points KISS-ICP registered against the map
    sigma: float = _num(lo=0.0, hi=1e6, nan=True)  # KISS-ICP adaptive threshold after this scan
    detail: str = _text("")
    pose: np.ndarray = _array(ArraySpec("<f8", (4, 4), values="nan-or-rigid"))  # all NaN: no pose
    # Version 2
    epoch: int = _num(0, bounds=SEQ)  # echo of Scan.epoch
    edge: str = _text("", max_len=ID_MAX)  # the answering edge


@dataclass(frozen=True)
class Frame(Message):
    """One camera frame, robot → edge detector. ``encoding`` "bgr8" (raw, ``height*width*3``
    bytes) or "jpeg"."""

    TYPE: ClassVar[str] = "frame"
    robot: str = _text(ident=True)
    seq: int = _num(bounds=SEQ)
    send_stamp: float = _num(bounds=STAMP)  # robot clock, echoed back in the detections
    capture_stamp: float = _num(bounds=STAMP)  # robot clock when the camera delivered the frame
    encoding: str = _text(choices=("bgr8", "jpeg"))
    width: int = _num(lo=1, hi=65_535)
    height: int = _num(lo=1, hi=65_535)
    data: np.ndarray = _array(ArraySpec("|u1", (-1,)))
    # Version 2
    edge: str = _text("", max_len=ID_MAX)  # the edge asked to detect it ("": any edge that hears it)
    # Version 3: the camera's size when the frame was shrunk on the way (0: not shrunk). The edge
    # answers with boxes in the camera's pixels, scaled from the frame's.
    camera_width: int = _num(0, lo=0, hi=65_535, since=3)
    camera_height: int = _num(0, lo=0, hi=65_535, since=3)
    # Version 4: the highest codec version the robot reads (3: not said). Set to 4 only for an edge
    # that reads 4; the edge then stamps its answer with the frame's arrival (edge clock).
    reads: int = _num(3, lo=1, hi=1_000, since=4)

    def check_size(self, limits: Limits = DEFAULT_LIMITS) -> None:
        """``WireError`` unless the declared size is within the pixel cap and, for raw frames,
        the data is exactly that size (a JPEG's own header is checked before it is decoded)."""
        if self.width * self.height > limits.max_pixels:
            raise WireError(f"frame of {self.width}x{self.height} pixels (at most {limits.max_pixels})")
        if self.encoding == "bgr8" and self.data.size != self.width * self.height * 3:
            raise WireError(f"bgr8 frame of {self.data.size} bytes, {self.width}x{self.height}x3 = "
                            f"{self.width * self.height * 3} expected")
        if (self.camera_width == 0) != (self.camera_height == 0):
            raise WireError(f"camera size {self.camera_width}x{self.camera_height}: both or neither")
        if self.camera_width and (self.camera_width < self.width or self.camera_height < self.height):
            raise WireError(f"camera size {self.camera_width}x{self.camera_height} below the frame's "
                            f"{self.width}x{self.height} (a frame is only ever shrunk)")

    def camera_size(self) -> tuple[int, int]:
        """(width, height) of the camera's frame: the boxes' pixels in the edge's answer."""
        return (self.camera_width, self.camera_height) if self.camera_width else (self.width, self.height)


@dataclass(frozen=True)
class Detections(Message):
    """The edge detector's answer to one frame; boxes (x1, y1, x2, y2) in the camera's pixels (the
    frame's, scaled up to its ``camera_size`` when it was shrunk on the way)."""

    TYPE: ClassVar[str] = "detections"
    robot: str = _text(ident=True)
    seq: int = _num(bounds=SEQ)
    send_stamp: float = _num(bounds=STAMP)  # echo of Frame.send_stamp (robot clock)
    edge: str = _text(ident=True)
    model: str = _text(max_len=ID_MAX)
    status: str = _text(choices=("ok", "error", "dropped"))  # "error": undecodable; "dropped": not served
    # (a newer frame of the robot came behind it, its queue overflowed, or the robot was evicted)
    infer_time: float = _num(bounds=DURATION)  # edge inference [s]
    queue_time: float = _num(bounds=DURATION)  # waiting on the edge before inference [s]
    batch: int = _num(lo=0, hi=1e6)  # frames served in the same pass as this one
    detail: str = _text("")
    boxes: np.ndarray = _array(ArraySpec("<f4", (-1, 4), cap="max_detections"))
    scores: np.ndarray = _array(ArraySpec("<f4", (-1,), cap="max_detections"))
    classes: np.ndarray = _array(ArraySpec("<i4", (-1,), cap="max_detections"))
    # Version 4, only in answers to frames whose robot reads 4: the edge's monotonic clock [s] when
    # the frame arrived (NaN: not stamped). Only differences between one edge's stamps mean anything.
    arrival: float = _num(NAN, lo=-1e12, hi=1e12, nan=True, since=4)

    def __post_init__(self) -> None:
        if not len(self.boxes) == len(self.scores) == len(self.classes):
            raise WireError(f"detections: {len(self.boxes)} boxes, {len(self.scores)} scores, "
                            f"{len(self.classes)} classes")


@dataclass(frozen=True)
class MapReply(Message):
    """A robot's registered map and trajectory, answered by the edge's map queryable."""

    TYPE: ClassVar[str] = "map"
    robot: str = _text(ident=True)
    scans: int = _num(lo=0, hi=SEQ_MAX)
    points: np.ndarray = _array(ArraySpec("<f4", (-1, 3), cap="max_map_points"))
    seqs: np.ndarray = _array(ArraySpec("<i8", (-1,), cap="max_map_points"))
    poses: np.ndarray = _array(ArraySpec("<f8", (-1, 4, 4), values="rigid", cap="max_map_points"))
    # Version 7: the answering edge ("": an edge older than per-edge map keys, on the key before
    # them); a querier drops a reply naming another edge than it asked (runtime/maps.py)
    edge: str = _text("", max_len=ID_MAX, since=7)


@dataclass(frozen=True)
class Pong(Message):
    """Answer to a ping query: the edge's id, echoing the robot's stamp."""

    TYPE: ClassVar[str] = "pong"
    edge: str = _text(ident=True)
    stamp: float = _num(lo=-1e12, hi=1e12, nan=True)


@dataclass(frozen=True)
class Status(Message):
    """Counters and gauges of one daemon, published about once a second."""

    TYPE: ClassVar[str] = "status"
    source: str = _text(choices=("robot", "edge"))
    id: str = _text(ident=True)
    stamp: float = _num(bounds=STAMP)
    values: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Checkpoint(Message):
    """A robot's mapping state, compact enough to send every few scans: the edge sends it to its
    robot, which holds the latest, so the next edge (or the robot's own odometry) continues the
    trajectory in the same frame. Also built by the robot from its local odometry."""

    TYPE: ClassVar[str] = "checkpoint"
    robot: str = _text(ident=True)
    edge: str = _text(max_len=ID_MAX)  # who made it ("" = the robot itself)
    epoch: int = _num(bounds=SEQ)
    seq: int = _num(bounds=SEQ)  # the last scan registered
    stamp: float = _num(bounds=STAMP)  # robot wall clock of that scan (its capture stamp)
    voxel_size: float = _num(lo=1e-3, hi=100.0)  # the mapper's configuration
    max_range: float = _num(lo=0.1, hi=10_000.0)
    min_range: float = _num(lo=0.0, hi=10_000.0)
    max_points_per_voxel: int = _num(lo=1, hi=1000)
    pose: np.ndarray = _array(ArraySpec("<f8", (4, 4), values="rigid"))  # sensor → world after that scan
    delta: np.ndarray = _array(ArraySpec("<f8", (4, 4), values="rigid"))  # the last motion per scan period
    points: np.ndarray = _array(ArraySpec("<f4", (-1, 3), cap="max_map_points"))  # coarse local map, world
    final: bool = False  # the edge is draining: this is its last checkpoint, the robot must move
    # Version 6: the local map coded as a q16d scan payload (coding.py) instead of ``points`` (then
    # empty): ``n_points`` points on a ``quant_step`` grid from ``origin``
    quant_step: float = _num(0.0, lo=0.0, hi=1.0, since=6)
    n_points: int = _num(-1, lo=-1, hi=1e12, since=6)
    origin: np.ndarray | None = _array(ArraySpec("<f8", (3,)), optional=True, since=6)
    packed: np.ndarray | None = _array(ArraySpec("|u1", (-1,)), optional=True, since=6)
    # Version 8: the fastest yaw per scan period (rad) the mapper saw between registered scans (0:
    # not said); the next mapper turns its guesses after a gap by it (mapping/mapper.py)
    turn_rate: float = _num(0.0, lo=0.0, hi=math.pi, since=8)

    def __post_init__(self) -> None:
        if self.packed is not None and (self.origin is None or self.quant_step <= 0 or self.n_points < 0
                                        or len(self.points)):
            raise WireError("checkpoint: a coded local map needs its origin, step and point count, "
                            "and no float32 points beside it")

    def cloud(self, limits: Limits = DEFAULT_LIMITS) -> np.ndarray:
        """The local map as float32 (n, 3), decoded if coded; ``WireError`` if it cannot be."""
        if self.packed is None:
            return self.points
        from zoffload.protocol.coding import CodingError, decode_q16d

        if self.n_points > limits.max_checkpoint_points:
            raise WireError(f"checkpoint of {self.n_points} points (at most {limits.max_checkpoint_points})")
        if self.n_points > CODED_POINTS_PER_BYTE * max(len(self.packed), 1):
            raise WireError(f"checkpoint of {self.n_points} points in {len(self.packed)} bytes (at most "
                            f"{CODED_POINTS_PER_BYTE} points a byte)")
        assert self.origin is not None  # (__post_init__)
        if not np.all(np.abs(self.origin) <= ORIGIN_MAX):
            raise WireError(f"checkpoint origin {self.origin.tolist()} beyond {ORIGIN_MAX:g} m")
        try:
            return decode_q16d(self.packed, self.n_points, self.origin, self.quant_step)[0]
        except CodingError as exc:
            raise WireError(f"checkpoint: {exc}") from exc

    def readable_by(self, reads: int, limits: Limits = DEFAULT_LIMITS) -> Checkpoint:
        """The same checkpoint as a peer that reads codec version ``reads`` takes it: without the
        turn rate below 8, with its local map as float32 points (``plain``) below 6."""
        cp = self if reads >= 8 or not self.turn_rate else dataclasses.replace(self, turn_rate=0.0)
        return cp if reads >= 6 else cp.plain(limits)

    def plain(self, limits: Limits = DEFAULT_LIMITS) -> Checkpoint:
        """The same checkpoint with its local map as float32 points (for a peer that reads
        version 5 or older); ``WireError`` if the coded map does not decode."""
        if self.packed is None:
            return self
        return dataclasses.replace(self, points=self.cloud(limits), quant_step=0.0, n_points=-1, origin=None,
                                   packed=None)


@dataclass(frozen=True)
class Attach(Message):
    """A robot asking an edge to map it (the payload of a query on the edge's attach key): its
    sensor, the epoch it proposes, the checkpoint to continue from (an encoded ``Checkpoint``,
    empty for a fresh start) and the poses it estimated itself since that checkpoint."""

    TYPE: ClassVar[str] = "attach"
    robot: str = _text(ident=True)
    epoch: int = _num(bounds=SEQ)
    max_range: float = _num(lo=0.1, hi=10_000.0)
    voxel_max: float = _num(lo=0.0, hi=10.0)
    rate_hz: float = _num(lo=0.01, hi=1000.0)
    checkpoint: bytes = b""
    local_seqs: np.ndarray = _array(ArraySpec("<i8", (-1,), cap="max_map_points"))
    local_poses: np.ndarray = _array(ArraySpec("<f8", (-1, 4, 4), values="rigid", cap="max_map_points"))
    # Version 6: the newest codec version the robot reads (5: not said); 6 or more, the edge may
    # send it coded checkpoints
    reads: int = _num(5, lo=1, hi=1_000, since=6)
    # Version 9: the backfill, scans the robot registered itself while no edge mapped it (an
    # outage), each an encoded ``Scan`` at a coarse grid, concatenated, and their sizes in bytes:
    # a mapper that mapped the robot before registers them in order (mapping/mapper.py
    # ``continue_from``) instead of jumping the outage to the robot's pose
    backfill: np.ndarray | None = _array(ArraySpec("|u1", (-1,)), optional=True, since=9)
    backfill_sizes: np.ndarray | None = _array(ArraySpec("<i8", (-1,), cap="max_backfill_scans"),
                                               optional=True, since=9)
    # Version 10: the robot's own pose of each backfilled scan (its odometry's frame, the one its
    # local poses are in): the edge predicts the backfill's first scan from it when that scan
    # lies more than a few after the edge's last, with no local pose in between (an outage
    # longer than the robot's ring, up to the edge's ``max_gap`` scans after its last)
    backfill_poses: np.ndarray | None = _array(ArraySpec("<f8", (-1, 4, 4), values="rigid",
                                                         cap="max_backfill_scans"), optional=True, since=10)

    def __post_init__(self) -> None:
        if len(self.local_seqs) != len(self.local_poses):
            raise WireError(f"attach: {len(self.local_seqs)} seqs for {len(self.local_poses)} poses")
        if (self.backfill is None) != (self.backfill_sizes is None):
            raise WireError("attach: a backfill needs both its bytes and its sizes")
        if self.backfill is not None and self.backfill_sizes is not None:
            sizes = self.backfill_sizes.tolist()  # Python ints: a sum of int64s may wrap
            if sizes and (min(sizes) < 1 or sum(sizes) != len(self.backfill)):
                raise WireError(f"attach: backfill sizes summing to {sum(sizes)} for "
                                f"{len(self.backfill)} bytes (each at least 1)")
            if not len(sizes) and len(self.backfill):
                raise WireError(f"attach: {len(self.backfill)} backfill bytes without sizes")
        if self.backfill_poses is not None and (self.backfill_sizes is None
                                                or len(self.backfill_poses) != len(self.backfill_sizes)):
            n = 0 if self.backfill_sizes is None else len(self.backfill_sizes)
            raise WireError(f"attach: {len(self.backfill_poses)} backfill poses for {n} backfilled scans")

    def backfill_scans(self, limits: Limits = DEFAULT_LIMITS) -> list[Scan]:
        """The backfill's scans, decoded and checked as any scan (``WireError`` if one is not a
        valid scan of this robot, their seqs do not ascend, a coded one declares more than
        ``CODED_POINTS_PER_BYTE`` points a byte, or together they declare more than one scan's
        ``max_points``: a receiver decodes their points before registering them)."""
        if self.backfill is None or self.backfill_sizes is None:
            return []
        if len(self.backfill_sizes) > limits.max_backfill_scans:
            raise WireError(f"backfill of {len(self.backfill_sizes)} scans "
                            f"(at most {limits.max_backfill_scans})")
        data = memoryview(self.backfill.data)
        out: list[Scan] = []
        at = total = 0
        for size in self.backfill_sizes.tolist():
            scan = decode(data[at:at + size], expect=Scan, limits=limits)
            at += size
            if scan.robot != self.robot:
                raise WireError(f"backfill scan of robot {scan.robot!r} in {self.robot!r}'s attach")
            if out and scan.seq <= out[-1].seq:
                raise WireError(f"backfill seqs do not ascend ({out[-1].seq}, then {scan.seq})")
            coded = scan.coding != "f32"
            declared = scan.n_points if coded else len(scan.points)
            nbytes = len(scan.packed) if scan.packed is not None else 0
            if coded and declared > CODED_POINTS_PER_BYTE * max(nbytes, 1):
                raise WireError(f"backfill scan {scan.seq}: {declared} points in {nbytes} bytes")
            total += max(declared, 0)
            if total > limits.max_points:
                raise WireError(f"backfill of more than {limits.max_points} points")
            out.append(scan)
        return out


@dataclass(frozen=True)
class AttachReply(Message):
    """The edge's answer to an attach: accepted (mapping under ``epoch``) or refused, and why."""

    TYPE: ClassVar[str] = "attach_reply"
    robot: str = _text(ident=True)
    edge: str = _text(ident=True)
    epoch: int = _num(bounds=SEQ)
    accepted: bool = False
    detail: str = _text("")
    robots: int = _num(0, lo=0, hi=1e6)  # robots this edge maps now
    capacity: int = _num(0, lo=0, hi=1e6)  # robots it takes at most


@dataclass(frozen=True)
class Preview(Message):
    """A camera frame as the robot saw it, for viewers (a few per second, only while one listens):
    a small JPEG, where it was detected and the person boxes found, in the JPEG's pixels."""

    TYPE: ClassVar[str] = "preview"
    robot: str = _text(ident=True)
    seq: int = _num(bounds=SEQ)
    stamp: float = _num(bounds=STAMP)  # robot wall clock when the result came
    side: str = _text(choices=("local", "edge"))
    width: int = _num(lo=1, hi=4096)
    height: int = _num(lo=1, hi=4096)
    jpeg: np.ndarray = _array(ArraySpec("|u1", (-1,)))
    boxes: np.ndarray = _array(ArraySpec("<f4", (-1, 4), cap="max_detections"))
    scores: np.ndarray = _array(ArraySpec("<f4", (-1,), cap="max_detections"))


MESSAGES: dict[str, type[Message]] = {
    m.TYPE: m for m in (Scan, ScanAck, Frame, Detections, MapReply, Pong, Status, Checkpoint, Attach,
                        AttachReply, Preview)
}
M = TypeVar("M", bound=Message)


def reads_in(values: dict[str, float]) -> int:
    """The newest codec version a peer's status says it reads (``READS_KEY``): a whole number
    in 1..1000, else 3 (not said, as by a version-3 build, or not believed)."""
    v = values.get(READS_KEY)
    if v is None or not math.isfinite(v) or v != int(v) or not 1 <= v <= 1_000:
        return 3
    return int(v)


def check_id(value: str, what: str = "id") -> str:
    if not _ID.match(value):
        raise WireError(f"{what} {value[:80]!r}: not an id (1-64 letters, digits, '_', '-', '.')")
    return value


def _enc_array(arr: np.ndarray) -> dict[str, Any]:
    arr = np.ascontiguousarray(arr)
    # A byte view, not arr.tobytes(): msgpack copies a memoryview once, straight into its output
    # (measured ~30x faster than packing a fresh bytes object of a 1.3 MB scan).
    data = arr.data.cast("B") if arr.size else b""
    return {"nd": arr.dtype.str, "shape": list(arr.shape), "data": data}


def _dec_array(name: str, obj: Any, spec: ArraySpec, limits: Limits) -> np.ndarray:
    if not isinstance(obj, dict) or set(obj) != {"nd", "shape", "data"}:
        raise WireError(f"field {name!r}: not an encoded array")
    dtype_s, shape, data = obj["nd"], obj["shape"], obj["data"]
    if not isinstance(dtype_s, str) or not isinstance(data, bytes) or not isinstance(shape, list):
        raise WireError(f"field {name!r}: malformed array header")
    if len(shape) > 4 or not all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d < 2**40
                                 for d in shape):
        raise WireError(f"field {name!r}: bad shape {shape!r}")
    if dtype_s != spec.dtype:  # one dtype per field: nothing else is even parsed
        try:
            other = np.dtype(dtype_s)
        except Exception as exc:  # numpy raises TypeError, ValueError, SyntaxError for odd strings
            raise WireError(f"field {name!r}: unknown dtype {dtype_s[:40]!r}") from exc
        if other.hasobject:
            raise WireError(f"field {name!r}: object arrays are not allowed")
        raise WireError(f"field {name!r}: dtype {dtype_s!r} where {spec.dtype} is expected")
    dtype = np.dtype(spec.dtype)
    expected = math.prod(shape) * dtype.itemsize
    if len(data) != expected:
        raise WireError(
            f"field {name!r}: {len(data)} bytes for shape {shape} {dtype_s} ({expected} expected)"
        )
    if spec.cap is not None and shape and shape[0] > getattr(limits, spec.cap):
        raise WireError(f"field {name!r}: {shape[0]} rows (at most {getattr(limits, spec.cap)}, {spec.cap})")
    arr = spec.check(name, np.frombuffer(data, dtype=dtype).reshape(shape))
    spec.check_values(name, arr)
    return arr


def _both_nan(a: Any, b: Any) -> bool:
    return all(isinstance(x, (float, np.floating)) and math.isnan(x) for x in (a, b))


def encode(msg: Message) -> bytes:
    """Serialise a message to bytes (pass these to ``put()``)."""
    out: dict[str, Any] = {"v": BASE_VERSION, "t": msg.TYPE}
    for f in dataclasses.fields(msg):  # type: ignore[arg-type]
        value = getattr(msg, f.name)
        since = f.metadata.get("since", 1)
        spec = f.metadata.get("array")
        if spec is not None and value is None and f.metadata.get("optional"):
            continue
        if since > 2:
            if spec is None and (value == f.default or _both_nan(value, f.default)):
                continue  # a version-2 reader would refuse the field: not sent at its default
            out["v"] = max(out["v"], since)
        if spec is not None:
            value = _enc_array(spec.check(f.name, np.asarray(value)))
        elif isinstance(value, (np.floating, np.integer, np.bool_)):
            value = value.item()
        out[f.name] = value
    return msgpack.packb(out, use_bin_type=True)


_SCALARS: dict[Any, tuple[type, ...]] = {
    "int": (int,), "float": (float, int), "str": (str,), "bool": (bool,), "bytes": (bytes,),
    "dict[str, float]": (dict,),
}


def _check_scalar(kind: str, name: str, f: dataclasses.Field[Any], value: Any, limits: Limits) -> Any:
    allowed = _SCALARS.get(f.type, ())
    if (isinstance(value, bool) and f.type != "bool") or not isinstance(value, allowed):
        raise WireError(f"{kind}: field {name!r} has type {type(value).__name__}")
    return _check_value(kind, name, f, value, limits)


def _check_value(kind: str, name: str, f: dataclasses.Field[Any], value: Any, limits: Limits) -> Any:
    num: Num | None = f.metadata.get("num")
    if f.type == "float":
        value = float(cast(float, value))
        if math.isnan(value):
            if num is None or not num.nan:
                raise WireError(f"{kind}: field {name!r} is NaN")
        elif num is not None and not num.lo <= value <= num.hi:
            raise WireError(f"{kind}: field {name!r} = {value!r} outside [{num.lo}, {num.hi}]")
    elif f.type == "int" and num is not None and not num.lo <= value <= num.hi:
        raise WireError(f"{kind}: field {name!r} = {value} outside [{num.lo:g}, {num.hi:g}]")
    elif f.type == "str":
        if f.metadata.get("ident"):
            check_id(value, f"{kind}: field {name!r}")
        choices = f.metadata.get("choices")
        if choices and value not in choices:
            raise WireError(f"{kind}: field {name!r} = {value[:40]!r}, not one of {', '.join(choices)}")
        if len(value) > f.metadata.get("max_len", 1000):
            raise WireError(f"{kind}: field {name!r} longer than {f.metadata.get('max_len', 1000)}")
    elif f.type == "dict[str, float]":
        if len(value) > limits.max_status_values or not all(
            isinstance(k, str) and len(k) <= 128 and isinstance(v, (int, float)) and not isinstance(v, bool)
            and not (isinstance(v, float) and math.isinf(v))
            for k, v in value.items()
        ):
            raise WireError(f"{kind}: field {name!r} must map at most {limits.max_status_values} names to "
                            "numbers (finite or NaN)")
    return value


PEEK_KEYS = 64  # a message map has fewer fields than this; a hostile one is not read further


def _unique_keys(pairs: Iterable[tuple[Any, Any]]) -> dict[Any, Any]:
    """A map with each key once: msgpack keeps the last of a repeated key, and ``peek_fields``
    (which reads a scan's route cheaply) the first; a message saying two things is refused.
    (msgpack's C extension passes a list, its pure-Python fallback a generator.)"""
    pairs = list(pairs)
    out = dict(pairs)
    if len(out) != len(pairs):
        raise ValueError("a key repeated in a map")
    return out


def peek_fields(data: bytes | bytearray | memoryview, msg_type: str, names: tuple[str, ...]
                ) -> dict[str, Any] | None:
    """Some top-level fields of an encoded message, read without decoding it: every other value
    (arrays included) is stepped over by msgpack, never built. Fields that are absent are left out
    (a version-1 sender has no ``edge``). None when the bytes are not a message map, its ``t``
    names another type, or they break off; nothing is checked beyond that (``decode`` judges
    the message). For deciding cheaply whose message it is (another edge's scan or frame)."""
    try:
        unpacker = msgpack.Unpacker(raw=False, max_buffer_size=max(len(data), 1), strict_map_key=True,
                                    max_ext_len=0)
        unpacker.feed(data)
        found: dict[str, Any] = {}
        for _ in range(min(unpacker.read_map_header(), PEEK_KEYS)):
            key = unpacker.unpack()
            if key == "t":
                if unpacker.unpack() != msg_type:
                    return None
            elif key in names:
                found[key] = unpacker.unpack()
            else:
                unpacker.skip()
    except Exception:  # msgpack raises several unrelated types for broken input
        return None
    return found


@overload
def decode(data: bytes | bytearray | memoryview, expect: type[M], limits: Limits = ...) -> M: ...


@overload
def decode(data: bytes | bytearray | memoryview, expect: None = None, limits: Limits = ...) -> Message: ...


def decode(data: bytes | bytearray | memoryview, expect: type[Message] | None = None,
           limits: Limits = DEFAULT_LIMITS) -> Message:
    """Parse bytes into a message, checking every field; raise ``WireError`` (and nothing else)
    on anything off. With ``expect``, any other message type is a ``WireError`` and the result
    is typed."""
    try:
        return _decode(data, expect, limits)
    except WireError:
        raise
    except Exception as exc:  # a case the checks above missed must still not escape as a crash
        raise WireError(f"undecodable: {exc.__class__.__name__}: {str(exc)[:200]}") from exc


def _decode(data: bytes | bytearray | memoryview, expect: type[Message] | None, limits: Limits) -> Message:
    if len(data) > limits.max_bytes:
        raise WireError(f"{len(data)} bytes (at most {limits.max_bytes})")
    try:
        # Containers and strings can be no longer than the payload itself: msgpack must not
        # pre-allocate what a forged length prefix claims
        n = len(data)
        obj = msgpack.unpackb(data, raw=False, strict_map_key=True, max_str_len=n, max_bin_len=n,
                              max_array_len=n, max_map_len=n, max_ext_len=0, object_pairs_hook=_unique_keys)
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise WireError(f"not msgpack: {exc.__class__.__name__}: {str(exc)[:200]}") from exc
    if not isinstance(obj, dict):
        raise WireError("not a message map")
    version = obj.pop("v", None)
    if version not in READS or isinstance(version, bool):
        raise WireError(f"codec version {version!r}, this build reads {', '.join(map(str, READS))}")
    kind = obj.pop("t", None)
    cls = MESSAGES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise WireError(f"unknown message type {str(kind)[:40]!r}")
    if expect is not None and cls is not expect:
        raise WireError(f"got a {kind!r} message where {expect.TYPE!r} is expected")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    extra = set(obj) - set(fields)
    if extra:
        raise WireError(f"{kind}: unknown fields {sorted(str(e)[:40] for e in extra)[:10]}")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in obj:
            if f.default is not dataclasses.MISSING and ("array" not in f.metadata
                                                         or f.metadata.get("optional")):
                continue
            if f.default_factory is not dataclasses.MISSING:
                continue
            raise WireError(f"{kind}: missing field {name!r}")
        value = obj[name]
        spec = f.metadata.get("array")
        kwargs[name] = (_dec_array(name, value, spec, limits) if spec is not None
                        else _check_scalar(kind, name, f, value, limits))
    return cls(**kwargs)
