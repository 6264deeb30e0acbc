"""The rmw_zenoh attachment, byte for byte (attachment_helpers.cpp; zenoh-ext serialization)."""

from __future__ import annotations

import struct

import pytest
from zenoh import ext

from zoffload.ros2.attachment import PLAIN_SIZE, Attachment, AttachmentError, parse_attachment

GID = bytes(range(16))
TS = 1700000000123456789


def test_plain_format_is_the_33_bytes_rmw_zenoh_writes() -> None:
    data = Attachment(5, TS, GID).pack()
    assert len(data) == PLAIN_SIZE
    assert data.hex() == "050000000000000015cd853dfe9c971710000102030405060708090a0b0c0d0e0f"
    assert data == struct.pack("<qqB16s", 5, TS, 16, GID)
    # the same bytes as zenoh-ext's serializer (what AttachmentData::serialize_to_zbytes uses)
    assert data == ext.z_serialize((ext.Int64(5), ext.Int64(TS), GID)).to_bytes()
    assert parse_attachment(data) == Attachment(5, TS, GID)


def test_keyed_format_of_jazzy_before_0_2_4() -> None:
    data = Attachment(16, TS, GID).pack(keyed=True)
    assert len(data) == 77
    assert data == ext.z_serialize(("sequence_number", ext.Int64(16), "source_timestamp", ext.Int64(TS),
                                    "source_gid", GID)).to_bytes()
    # seq 16 puts 0x10 at byte 16 as in the plain format: the key decides
    assert parse_attachment(data) == Attachment(16, TS, GID)


def test_trailing_bytes_are_tolerated_and_garbage_refused() -> None:
    assert parse_attachment(Attachment(1, 2, GID).pack() + b"xx").seq == 1
    for bad in (b"", b"\x00" * 32, b"\x00" * 16 + b"\x0f" + b"\x00" * 16,
                b"\x0fsequence_number" + b"\x00" * 8,
                Attachment(1, 2, GID).pack(keyed=True)[:-1]):
        with pytest.raises(AttachmentError):
            parse_attachment(bad)
    with pytest.raises(AttachmentError):
        Attachment(1, 2, b"short").pack()
