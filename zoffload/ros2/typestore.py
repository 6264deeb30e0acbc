"""ROS 2 message types, their RIHS01 hashes and CDR (de)serialisation, from ``rosbags``.

rmw_zenoh's payload is classic CDR (XCDR1) after a 4-byte encapsulation header (``00 01 00 00``
little-endian), the bytes rosbags' ``serialize_cdr`` writes and rosbag2 stores. The type store is
Jazzy's (the hashes of the types used here are the same in Humble, Jazzy, Kilted and Lyrical);
vision_msgs, not bundled with rosbags, is registered from its 4.1.1 definitions (Jazzy 4.1.1 and
Kilted/Rolling 4.2.0 have the same ``msg/`` files, so the same hashes).
"""

from __future__ import annotations

import threading
from typing import Any

# vision_msgs 4.1.1 (ros-perception/vision_msgs): field names and types, comments dropped (they
# do not enter the RIHS01 hash)
VISION_MSGS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"),
    "vision_msgs/msg/Detection2D": (
        "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox2D bbox\nstring id\n"),
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nDetection2D[] detections\n",
}

_lock = threading.Lock()
_store: Any = None


class MessageError(ValueError):
    """A payload that is not a valid CDR message of the expected type (truncated, forged
    lengths, wrong encapsulation), or a type the store does not know."""


def rosbags_typesys() -> Any:
    try:
        import rosbags.typesys as typesys
    except ImportError as exc:
        raise ImportError("ROS 2 messages and bags need rosbags: pip install 'zoffload[ros]'") from exc
    return typesys


def typestore() -> Any:
    """The shared type store: ROS 2 Jazzy's types plus vision_msgs."""
    global _store
    with _lock:
        if _store is None:
            typesys = rosbags_typesys()
            store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
            extra: dict[str, Any] = {}
            for name, text in VISION_MSGS.items():
                extra.update(typesys.get_types_from_msg(text, name))
            store.register(extra)
            _store = store
        return _store


def msg_class(msgtype: str) -> Any:
    """The rosbags dataclass of ``pkg/msg/Name`` (all fields are keyword arguments)."""
    try:
        return typestore().types[msgtype]
    except KeyError as exc:
        raise MessageError(f"unknown ROS 2 message type {msgtype!r}") from exc


def type_hash(msgtype: str) -> str:
    """``RIHS01_`` + 64 hex digits, as ``ros2 topic info -v`` shows it."""
    msg_class(msgtype)
    return str(typestore().hash_rihs01(msgtype))


def serialize(msg: Any, msgtype: str) -> bytes:
    """CDR bytes with the little-endian encapsulation header."""
    return bytes(typestore().serialize_cdr(msg, msgtype))


def deserialize(data: bytes | memoryview, msgtype: str) -> Any:
    """The message; ``MessageError`` and nothing else for any bytes (rosbags checks every
    sequence length against the payload before it allocates)."""
    if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
        raise MessageError(f"{msgtype}: {len(data)} bytes without a CDR encapsulation header")
    try:
        return typestore().deserialize_cdr(data, msgtype)
    except Exception as exc:  # rosbags raises SerdeError, and struct/index errors on odd bytes
        what = f"{exc.__class__.__name__}: {str(exc)[:200]}"
        raise MessageError(f"{msgtype}: undecodable CDR ({what})") from exc
