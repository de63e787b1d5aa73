"""The .msg texts alone (rosbags typestore) encode and decode exactly what rclpy does."""

from __future__ import annotations

import pytest
from conftest import REPO
from rclpy.serialization import deserialize_message, serialize_message
from rosmsg_util import (
    fill_rclpy,
    rclpy_to_dict,
    rclpy_type,
    rosbags_msg,
    rosbags_to_dict,
    sample_values,
)

from haptic_topology.messages import definitions as msgdefs
from haptic_topology.messages.definitions import (
    MESSAGE_NAMES,
    type_name,
    typestore_with_haptic_msgs,
)


@pytest.mark.parametrize('name', MESSAGE_NAMES)
def test_rosbags_cdr_matches_rclpy(name: str) -> None:
    store = typestore_with_haptic_msgs()
    full = type_name(name)
    values = sample_values(store, full)
    ours = bytes(store.serialize_cdr(rosbags_msg(store, full, values), full))
    theirs = bytes(serialize_message(fill_rclpy(rclpy_type(name)(), values)))

    # Each side decodes the other's bytes to the full sample ...
    assert rosbags_to_dict(store, full, store.deserialize_cdr(theirs, full)) == values
    assert rclpy_to_dict(deserialize_message(ours, rclpy_type(name))) == values
    assert rosbags_to_dict(store, full, store.deserialize_cdr(ours, full)) == values
    # ... and the bytes are identical except alignment padding, which Fast-CDR leaves
    # uninitialised. (Same length, and every value byte decodes identically above, so a byte
    # that differs carries no value; rosbags writes such bytes as zero.)
    assert len(ours) == len(theirs)
    assert ours[:4] == theirs[:4] == b'\x00\x01\x00\x00'  # CDR little-endian header
    differing = [i for i in range(len(ours)) if ours[i] != theirs[i]]
    assert all(ours[i] == 0 for i in differing)


def test_message_definitions_cover_every_message() -> None:
    defs = msgdefs.message_definitions()
    assert sorted(defs) == sorted(type_name(n) for n in MESSAGE_NAMES)
    assert all('std_msgs/Header header' in text for text in defs.values())


def test_installed_definitions_equal_source() -> None:
    source = msgdefs.message_definitions(REPO / 'msg_schemas' / 'msg')
    assert msgdefs.message_definitions() == source, (
        'installed .msg files differ from msg_schemas/: run `make setup`'
    )


def test_constants_are_registered() -> None:
    store = typestore_with_haptic_msgs()
    state = store.types[type_name('DeviceState')]
    assert state.STATUS_WATCHDOG == 4


def test_missing_directory_is_reported(tmp_path: object) -> None:
    with pytest.raises(msgdefs.MessageDefinitionError, match='DeviceState.msg'):
        msgdefs.message_definitions(tmp_path)  # type: ignore[arg-type]
