"""The attachment rmw_zenoh sends with every sample, and drops samples without.

``AttachmentData`` in rmw_zenoh_cpp ``src/detail/attachment_helpers.cpp``, serialised with
zenoh-ext's serializer (little-endian, sequences prefixed by a LEB128 length):

* plain, 33 bytes (Jazzy ≥ 0.2.4, Kilted, Rolling ≥ 0.6): int64 sequence number (from 1), int64
  source timestamp (ns since the Unix epoch), ``0x10``, the publisher's 16-byte GID;
* keyed, 77 bytes (Jazzy 0.2.0-0.2.3, Rolling 0.3-0.5): the same values, each after its name as a
  length-prefixed string (``sequence_number``, ``source_timestamp``, ``source_gid``).

A ROS node fails on the format it does not expect (an exception in its Zenoh callback), so a
publisher must send the one its peers read; a receiver here reads both.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

PLAIN_SIZE = 33
GID_SIZE = 16
_PLAIN = struct.Struct("<qqB16s")
_KEYS = (b"sequence_number", b"source_timestamp", b"source_gid")


class AttachmentError(ValueError):
    """Bytes that are neither attachment format."""


@dataclass(frozen=True)
class Attachment:
    seq: int
    stamp_ns: int  # the publisher's wall clock when it published
    gid: bytes  # 16 bytes naming the publisher

    def pack(self, keyed: bool = False) -> bytes:
        """The attachment bytes: plain (current rmw_zenoh) or ``keyed`` (Jazzy ≤ 0.2.3)."""
        if len(self.gid) != GID_SIZE:
            raise AttachmentError(f"a GID has {GID_SIZE} bytes, not {len(self.gid)}")
        if not keyed:
            return _PLAIN.pack(self.seq, self.stamp_ns, GID_SIZE, self.gid)
        seq_key, stamp_key, gid_key = (bytes([len(k)]) + k for k in _KEYS)
        return (seq_key + struct.pack("<q", self.seq) + stamp_key + struct.pack("<q", self.stamp_ns)
                + gid_key + bytes([GID_SIZE]) + self.gid)


def parse_attachment(data: bytes) -> Attachment:
    """Either format; ``AttachmentError`` for anything else. Trailing bytes are tolerated, as
    rmw_zenoh's member-wise reader does."""
    if len(data) >= PLAIN_SIZE and data[16] == GID_SIZE and not data.startswith(b"\x0fsequence_number"):
        seq, stamp, _, gid = _PLAIN.unpack_from(data)
        return Attachment(seq, stamp, gid)
    pos, values = 0, []
    for key, size in zip(_KEYS, (8, 8, 1 + GID_SIZE), strict=True):
        chunk = bytes([len(key)]) + key
        if data[pos:pos + len(chunk)] != chunk or len(data) < pos + len(chunk) + size:
            raise AttachmentError(f"{len(data)} bytes that are not an rmw_zenoh attachment "
                                  f"({PLAIN_SIZE} bytes: seq, stamp, 0x10, GID)")
        pos += len(chunk)
        values.append(data[pos:pos + size])
        pos += size
    if values[2][0] != GID_SIZE:
        raise AttachmentError(f"keyed attachment with a GID of {values[2][0]} bytes")
    return Attachment(struct.unpack("<q", values[0])[0], struct.unpack("<q", values[1])[0],
                      bytes(values[2][1:]))
