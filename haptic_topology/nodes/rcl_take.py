"""``rcl_take_serialized_message`` through ``ctypes``: serialized messages with the whole
``rmw_message_info_t``, including the publisher's gid, which rclpy 7.1's ``take_message``
leaves out (it gives the timestamps and sequence numbers only).

The structures mirror Jazzy's ``rmw/types.h`` (``rmw_message_info_t``: 64 bytes, the gid's
16 bytes at offset 40) and ``rcutils/types/uint8_array.h``; the functions come from the
``librcl.so`` and ``librcutils.so`` that rclpy's extension has loaded (one copy of rcl and of
its rmw in the process). One :class:`SerializedTaker` per subscription; its buffer is
allocated once and grows to the largest message taken, so a take copies the bytes once
(about 3 us a message, as rclpy's own raw take).
"""

from __future__ import annotations

import ctypes
import sys
from typing import Any

from haptic_topology.errors import BagError

RCL_RET_OK = 0
RCL_RET_SUBSCRIPTION_TAKE_FAILED = 401
#: ``RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED``: the rmw gives no sequence numbers
SEQUENCE_NUMBER_UNSUPPORTED = (1 << 64) - 1
#: First capacity of the take buffer (bytes; rmw grows it to a larger message)
INITIAL_CAPACITY = 4096

#: A publisher's gid as two native 64-bit words (cheap to read and hash per message)
Gid = tuple[int, int]


class _Allocator(ctypes.Structure):
    _fields_ = [('allocate', ctypes.c_void_p), ('deallocate', ctypes.c_void_p),
                ('reallocate', ctypes.c_void_p), ('zero_allocate', ctypes.c_void_p),
                ('state', ctypes.c_void_p)]


class _SerializedMessage(ctypes.Structure):      # rcutils_uint8_array_t
    _fields_ = [('buffer', ctypes.c_void_p), ('buffer_length', ctypes.c_size_t),
                ('buffer_capacity', ctypes.c_size_t), ('allocator', _Allocator)]


class MessageInfo(ctypes.Structure):
    """``rmw_message_info_t`` (times in ns since the epoch; ``gid_0``, ``gid_1``: the
    16 bytes of ``publisher_gid.data`` as native words, see :func:`gid_bytes`)."""

    _fields_ = [('source_timestamp', ctypes.c_int64), ('received_timestamp', ctypes.c_int64),
                ('publication_sequence_number', ctypes.c_uint64),
                ('reception_sequence_number', ctypes.c_uint64),
                ('gid_implementation', ctypes.c_char_p),
                ('gid_0', ctypes.c_uint64), ('gid_1', ctypes.c_uint64),
                ('from_intra_process', ctypes.c_bool)]


class _ErrorString(ctypes.Structure):
    _fields_ = [('str', ctypes.c_char * 1024)]


def gid_bytes(gid: Gid) -> bytes:
    """The 16 bytes of a gid, as rclpy's ``TopicEndpointInfo.endpoint_gid`` gives them."""
    return b''.join(w.to_bytes(8, sys.byteorder) for w in gid)


def gid_of(data: bytes) -> Gid:
    """The gid of its 16 bytes (:func:`gid_bytes` reversed)."""
    return (int.from_bytes(data[:8], sys.byteorder), int.from_bytes(data[8:16], sys.byteorder))


def _loaded(name: str) -> ctypes.CDLL:
    """The library ``name`` already mapped into this process (by rclpy), else by name."""
    with open('/proc/self/maps') as maps:
        for line in maps:
            path = line.split()[-1]
            if path.endswith(f'/{name}'):
                return ctypes.CDLL(path)
    return ctypes.CDLL(name)


class _Lib:
    def __init__(self) -> None:
        assert ctypes.sizeof(MessageInfo) == 64 and ctypes.sizeof(_SerializedMessage) == 64
        rcl, rcutils = _loaded('librcl.so'), _loaded('librcutils.so')
        self.take = rcl.rcl_take_serialized_message
        self.take.argtypes = [ctypes.c_void_p] * 4
        self.take.restype = ctypes.c_int
        self.default_allocator = rcutils.rcutils_get_default_allocator
        self.default_allocator.restype = _Allocator
        self.array_init = rcutils.rcutils_uint8_array_init
        self.array_init.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
        self.array_fini = rcutils.rcutils_uint8_array_fini
        self.array_fini.argtypes = [ctypes.c_void_p]
        self.error_string = rcutils.rcutils_get_error_string
        self.error_string.restype = _ErrorString
        self.reset_error = rcutils.rcutils_reset_error


_lib: _Lib | None = None


class SerializedTaker:
    """Takes the serialized messages waiting in one rclpy subscription (see module doc)."""

    def __init__(self, subscription: Any) -> None:
        global _lib
        if _lib is None:
            _lib = _Lib()
        self._lib = _lib
        self.subscription = subscription
        self._msg = _SerializedMessage()
        allocator = _lib.default_allocator()
        if _lib.array_init(ctypes.byref(self._msg), INITIAL_CAPACITY, ctypes.byref(allocator)):
            raise MemoryError(f'{subscription.topic_name}: no take buffer of '
                              f'{INITIAL_CAPACITY} bytes')
        self.info = MessageInfo()
        self._open = True

    def take_into(self, items: list[tuple[int, int, bytes]], index: int,
                  last_seq: dict[Gid, int], skipped: dict[Gid, int], now: int) -> int:
        """Append ``(index, receive time ns, serialized)`` for every message waiting (``now``
        where DDS gives no receive time); per publisher gid, keep the last sequence number
        taken in ``last_seq`` and add the numbers skipped since (sent, never taken) to
        ``skipped``. Return how many were taken."""
        take, handle, msg, info = self._lib.take, self.subscription.handle, self._msg, self.info
        pmsg, pinfo, string_at = ctypes.byref(msg), ctypes.byref(info), ctypes.string_at
        n = 0
        with handle:
            ptr = handle.pointer
            while (ret := take(ptr, pmsg, pinfo, None)) == RCL_RET_OK:
                gid, seq = (info.gid_0, info.gid_1), info.publication_sequence_number
                last = last_seq.get(gid)
                if last is not None and seq > last + 1 and seq != SEQUENCE_NUMBER_UNSUPPORTED:
                    skipped[gid] = skipped.get(gid, 0) + seq - last - 1
                last_seq[gid] = seq
                items.append((index, info.received_timestamp or now,
                              string_at(msg.buffer, msg.buffer_length)))
                n += 1
        if ret != RCL_RET_SUBSCRIPTION_TAKE_FAILED:      # nothing left: the normal end
            text = self._lib.error_string().str.decode(errors='replace')
            self._lib.reset_error()
            raise BagError(f'{self.subscription.topic_name}: taking a message failed '
                           f'(rcl return code {ret}): {text}')
        return n

    def destroy(self) -> None:
        """Free the take buffer (once; the subscription is the caller's)."""
        if self._open:
            self._open = False
            self._lib.array_fini(ctypes.byref(self._msg))
