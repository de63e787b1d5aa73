"""The device network protocol: one COMMAND or STATE per UDP datagram, fixed size, CRC32.

(One module of ~540 lines on purpose: the packet layouts, their encoding and decoding and the
session and sequence rules must agree byte for byte, and a device vendor reads them in one
place.)

A device controller on its own real-time computer (the paper's maglev had one) and the
``device_driver`` of this package talk over UDP: the driver's
:class:`~haptic_topology.remote.network.NetworkBackend` sends one COMMAND per device cycle,
the device (here :mod:`haptic_topology.remote.server`, the simulated maglev served at its own
1 kHz clock) answers every one of its own cycles with a STATE. No ROS, no rclpy: ``struct``,
``zlib`` and, for an authenticated link, ``hashlib`` only.

**Layout.** Little-endian, no padding between fields, fixed size for a given packet type and
task dimension ``m`` (3 planar, 6 spatial). Units SI; frames and vector layouts as the
``haptic_topology_msgs/DeviceState`` message (the device base frame, axes as the virtual
environment's world frame; planar ``pose = [x (m), y (m), theta (rad)]``, ``twist = [vx, vy
(m/s), wz (rad/s)]``, wrenches ``[fx, fy (N), tz (N m)]``; spatial ``pose = [x, y, z (m), rx,
ry, rz (rad, rotation vector)]``, ``twist = [vx, vy, vz (m/s), wx, wy, wz (rad/s)]``, wrenches
``[fx, fy, fz (N), tx, ty, tz (N m)]``).

Header, 48 bytes, every packet:

======  =====  ==============  =================================================================
offset  bytes  type            field
======  =====  ==============  =================================================================
0       4      char[4]         ``magic`` = ``b'HTDP'``
4       1      uint8           ``version`` = 1
5       1      uint8           ``type``: 1 COMMAND, 2 STATE (:class:`PacketType`)
6       2      uint16          ``flags``: COMMAND :class:`CommandFlags`; STATE 0
8       1      uint8           ``m``: task dimension, 3 or 6
9       3      -               reserved, sent as 0, ignored
12      4      uint32          ``session``: nonzero, drawn at random by the sender when it
                               starts (a client per activation, a server per process): a new
                               session is a restarted peer, its ``seq`` starts again at 1
16      8      uint64          ``seq``: 1, 2, 3, ... per sender session (>= 1)
24      8      uint64          ``stamp_ns``: the sender's monotonic clock at sending (ns); only
                               the sender compares it (round trip through ``echo_stamp_ns``)
32      8      uint64          ``echo_seq``: newest ``seq`` received from the peer's session
                               (0: none yet)
40      8      uint64          ``echo_stamp_ns``: that packet's ``stamp_ns`` (0: none)
======  =====  ==============  =================================================================

COMMAND body (client -> device), 8 + 8 m bytes, then the CRC:

======  ======  ==============  ================================================================
offset  bytes   type            field
======  ======  ==============  ================================================================
48      4       uint32          ``ttl_us``: validity (us, >= 1): the device applies the command
                                for at most this long after it arrived (and at most its own
                                command timeout)
52      4       -               reserved, sent as 0, ignored
56      8 m     float64[m]      ``wrench``: the control wrench u (N, N m), finite
======  ======  ==============  ================================================================

STATE body (device -> client), 16 + 32 m bytes, then the CRC:

========  ======  ============  ================================================================
offset    bytes   type          field
========  ======  ============  ================================================================
48        4       uint32        ``status``: :class:`~haptic_topology.vocabulary.DeviceStatus`
                                bits the device may report (``WORKSPACE_LIMIT`` 1,
                                ``SATURATED`` 2, ``FAULT`` 8) and the server's
                                :class:`ServerStatus` bits (from bit 16)
52        4       -             reserved, sent as 0, ignored
56        8       uint64        ``applied_seq``: ``seq`` of the command applied in the cycle
                                this state ends (0: none, the output was zero)
64        8 m     float64[m]    ``pose``
64+8m     8 m     float64[m]    ``twist``
64+16m    8 m     float64[m]    ``hand_wrench``: measured F_h of eq. 9 (N, N m)
64+24m    8 m     float64[m]    ``applied_wrench``: u applied in that cycle (N, N m)
========  ======  ============  ================================================================

Every packet ends with ``crc32`` (uint32): ``zlib.crc32`` of all the bytes before it. Sizes:
COMMAND 84 bytes (m = 3) / 108 (m = 6); STATE 164 / 260 (:func:`packet_size`).

**Refused packets** (:func:`decode` raises :class:`ProtocolError` with its
:class:`Malformed` reason, checked in this order): a datagram shorter than a header and CRC
(``SIZE``), another ``magic`` (``MAGIC``), another ``version`` (``VERSION``), an unknown or
unexpected ``type`` (``TYPE``), ``m`` not 3 or 6 or not the receiver's (``DIM``), a length
other than the type's size (``SIZE``), a CRC mismatch (``CRC``), session or seq 0, unknown flag
or status bits, ``ttl_us`` 0 (``FIELD``), a NaN or infinite number (``NON_FINITE``). A refused
packet is counted and dropped: nothing of it reaches the device or the driver.

**Sequence numbers** (:class:`SeqTracker`, per peer session): a packet with a ``seq`` above
the newest is *new* (the gap before it counts as ``lost``); the same ``seq`` again is a
``duplicate``; an older ``seq`` seen for the first time is ``late`` (reordered or delayed past
a newer one; it leaves ``lost``); older than the tracker's window (1024) is ``too_old``. Only
new packets are used: a receiver acts on the newest, never goes back.

**Authenticated link** (both sides configured with the same pre-shared key,
:mod:`haptic_topology.remote.auth`): ``version`` = 2 and the CRC32 is replaced by a trailer
of 24 bytes (COMMAND 104 / 128 bytes, STATE 184 / 280):

======  =====  ==============  =================================================================
offset  bytes  type            field
======  =====  ==============  =================================================================
n-24    4      uint32          ``peer_session``: the receiver's session this packet is sent to
                               (0: not known yet, or a monitor copy)
n-20    4      uint32          ``key_id``: id of the key (``auth.key_id_of``)
n-16    16     bytes           ``mac``: ``hashlib.blake2b(data[:n-16], key=key,
                               digest_size=16)``, over header, body, peer_session and key_id
======  =====  ==============  =================================================================

The receiver checks the MAC before it reads anything else of the datagram; a failure is
counted ``rejected_unauthenticated`` (a version-1 packet), ``rejected_wrong_key`` (another key
id) or ``rejected_mac`` (forged or corrupted). A receiver with a key takes no version-1
packet, one without a key no version-2 packet (``version``). Replays: within a session a
packet sent again is not newer than the newest taken (``duplicate``, ``late``,
``too_old``); a packet addressed to another session of the receiver (recorded before the
receiver restarted) and a packet of a sender session the receiver has left behind (ended,
or taken over by a newer one) are counted ``rejected_replay``. A device takes a COMMAND
addressed to ``peer_session`` 0 (a client that knows no state of this device yet) as an idle
one: it never applies its wrench.

Example (checked by
``test/unit/remote/test_device_network.py``): a tracker that receives seqs 1, 2, 5, 3,
3, 2, 6 has taken 4 new packets (1, 2, 5, 6), 1 late (3), 2 duplicates (the second 3, the
second 2) and counts 1 lost (4; 3 arrived late).
"""

from __future__ import annotations

import enum
import hmac
import math
import secrets
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from haptic_topology.errors import DeviceError
from haptic_topology.remote.auth import TAG_SIZE, LinkKey
from haptic_topology.vocabulary import DeviceStatus

MAGIC = b'HTDP'
#: ``version`` of an unauthenticated packet (CRC32 trailer).
VERSION = 1
#: ``version`` of an authenticated packet (MAC trailer).
VERSION_AUTH = 2
#: UDP port of ``haptic-topology device-server`` and of the ``network`` backend by default.
DEFAULT_PORT = 47001
#: Task dimensions the protocol carries (planar, spatial).
DIMS = (3, 6)
#: The header (see module doc): magic, version, type, flags, m, 3 reserved, session, seq,
#: stamp_ns, echo_seq, echo_stamp_ns.
_HEADER_FMT = '4sBBHB3xIQQQQ'
HEADER = struct.Struct('<' + _HEADER_FMT)
_CRC = struct.Struct('<I')
#: The authenticated trailer before the tag: peer_session, key_id.
_AUTH = struct.Struct('<II')
#: Bytes a trailer adds after the body: CRC32 (version 1) or peer, key id, tag (version 2).
TRAILER = {False: _CRC.size, True: _AUTH.size + TAG_SIZE}
#: Largest value of a uint64 field.
U64_MAX = 2**64 - 1


class PacketType(enum.IntEnum):
    """``type`` of the header."""

    COMMAND = 1
    STATE = 2


class CommandFlags(enum.IntFlag):
    """``flags`` of a COMMAND."""

    NONE = 0
    #: From an engaged device loop: a parked simulated device starts integrating at the first
    #: such command (as :class:`~haptic_topology.device.backend.SimMaglevBackend` does at its
    #: first ``write``). Without it the command is an idle one: the output is zero.
    ENGAGED = 1
    #: The client deactivates: zero output at once and end this session.
    RELEASE = 2


_COMMAND_FLAGS = int(CommandFlags.ENGAGED | CommandFlags.RELEASE)


class ServerStatus(enum.IntFlag):
    """``status`` bits of a STATE that the device server adds (bit 16 up; the low bits are
    :class:`~haptic_topology.vocabulary.DeviceStatus`)."""

    NONE = 0
    #: No valid command within the server's command timeout (or the command's ttl): the output
    #: is zero because the commands stopped.
    COMMAND_TIMEOUT = 1 << 16
    #: The simulated device is parked at its initial pose: no engaged command yet.
    PARKED = 1 << 17


#: Device bits a STATE may carry (``WATCHDOG`` and ``IDLE`` are the driver's own).
DEVICE_BITS = int(DeviceStatus.WORKSPACE_LIMIT | DeviceStatus.SATURATED | DeviceStatus.FAULT)
STATUS_MASK = DEVICE_BITS | int(ServerStatus.COMMAND_TIMEOUT | ServerStatus.PARKED)


class Malformed(enum.Enum):
    """Why a datagram was refused (see module doc); the value names the counter."""

    SIZE = 'size'
    MAGIC = 'magic'
    VERSION = 'version'
    TYPE = 'type'
    DIM = 'dim'
    CRC = 'crc'
    FIELD = 'field'
    NON_FINITE = 'non_finite'


class Rejected(enum.Enum):
    """Why an authenticated receiver refused a datagram (module doc, "Authenticated link");
    the value names the counter ``rejected_<value>``."""

    #: The tag does not match the contents: forged or corrupted.
    MAC = 'mac'
    #: The packet was made with another key (its key id is not the receiver's).
    WRONG_KEY = 'wrong_key'
    #: A version-1 packet (no MAC) at a receiver with a key.
    UNAUTHENTICATED = 'unauthenticated'
    #: A valid tag, but addressed to another session of the receiver, or of a sender session
    #: the receiver has left behind: recorded earlier and sent again.
    REPLAY = 'replay'


class ProtocolError(DeviceError):
    """A datagram that is not a valid packet (``reason``), or values that cannot be sent."""

    def __init__(self, reason: Malformed | Rejected, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def command_size(m: int, auth: bool = False) -> int:
    """Bytes of a COMMAND for task dimension ``m`` (84 for 3, 108 for 6; authenticated 104,
    128)."""
    return HEADER.size + 8 + 8 * m + TRAILER[auth]


def state_size(m: int, auth: bool = False) -> int:
    """Bytes of a STATE for task dimension ``m`` (164 for 3, 260 for 6; authenticated 184,
    280)."""
    return HEADER.size + 16 + 32 * m + TRAILER[auth]


def packet_size(ptype: PacketType, m: int, auth: bool = False) -> int:
    """Bytes of a packet of type ``ptype`` for task dimension ``m`` (``auth``: version 2)."""
    return command_size(m, auth) if ptype is PacketType.COMMAND else state_size(m, auth)


def new_session() -> int:
    """A random nonzero session id (uint32)."""
    return secrets.randbits(32) or 1


@dataclass(frozen=True, slots=True)
class Command:
    """A decoded COMMAND (fields as the module doc; ``wrench`` m values, N and N m)."""

    session: int
    seq: int
    stamp_ns: int
    echo_seq: int
    echo_stamp_ns: int
    flags: CommandFlags
    ttl_us: int
    wrench: np.ndarray
    #: Authenticated only: the receiver's session this was sent to (0: none known yet).
    peer_session: int = 0


@dataclass(frozen=True, slots=True)
class State:
    """A decoded STATE (fields as the module doc; vectors of m values)."""

    session: int
    seq: int
    stamp_ns: int
    echo_seq: int
    echo_stamp_ns: int
    status: int
    applied_seq: int
    pose: np.ndarray
    twist: np.ndarray
    hand_wrench: np.ndarray
    applied_wrench: np.ndarray
    #: Authenticated only: the receiver's session this was sent to (0: none, a monitor copy).
    peer_session: int = 0


_COMMAND_STRUCTS = {m: struct.Struct(f'<{_HEADER_FMT}I4x{m}d') for m in DIMS}
_STATE_STRUCTS = {m: struct.Struct(f'<{_HEADER_FMT}I4xQ{4 * m}d') for m in DIMS}


def _check_dim(m: int) -> None:
    if m not in DIMS:
        raise ProtocolError(Malformed.DIM, f'task dimension must be 3 or 6, got {m}')


def _check_u64(name: str, value: int) -> None:
    if not 0 <= value <= U64_MAX:
        raise ProtocolError(Malformed.FIELD, f'{name} must be in [0, 2^64 - 1], got {value}')


def _finite(values: Sequence[float], what: str) -> None:
    if all(map(math.isfinite, values)):
        return
    i = next(i for i, v in enumerate(values) if not math.isfinite(v))
    raise ProtocolError(Malformed.NON_FINITE, f'{what}[{i}] is {values[i]}: only finite '
                        'numbers are sent')


def _seal(struct_: struct.Struct, fields: tuple[object, ...], key: LinkKey | None,
          peer_session: int) -> bytes:
    body = struct_.pack(*fields)
    if key is None:
        return body + _CRC.pack(zlib.crc32(body))
    if not 0 <= peer_session < 2**32:
        raise ProtocolError(Malformed.FIELD, f'peer_session must be in [0, 2^32 - 1], got '
                            f'{peer_session}')
    body += _AUTH.pack(peer_session, key.key_id)
    return body + key.tag(body)


def _header_fields(ptype: PacketType, flags: int, m: int, session: int, seq: int,
                   stamp_ns: int, echo_seq: int, echo_stamp_ns: int,
                   key: LinkKey | None) -> tuple[object, ...]:
    if not 1 <= session < 2**32:
        raise ProtocolError(Malformed.FIELD, f'session must be in [1, 2^32 - 1], got {session}')
    if not 1 <= seq <= U64_MAX:
        raise ProtocolError(Malformed.FIELD, f'seq must be in [1, 2^64 - 1], got {seq}')
    _check_u64('stamp_ns', stamp_ns)
    _check_u64('echo_seq', echo_seq)
    _check_u64('echo_stamp_ns', echo_stamp_ns)
    return (MAGIC, VERSION if key is None else VERSION_AUTH, int(ptype), flags, m, session, seq,
            stamp_ns, echo_seq, echo_stamp_ns)


def encode_command(session: int, seq: int, stamp_ns: int, echo_seq: int, echo_stamp_ns: int,
                   flags: CommandFlags, ttl_us: int, wrench: Sequence[float] | np.ndarray,
                   key: LinkKey | None = None, peer_session: int = 0) -> bytes:
    """A COMMAND datagram; refuses (:class:`ProtocolError`) non-finite values, a wrench of
    another size than 3 or 6, out-of-range integers, unknown flags. With ``key``: version 2,
    addressed to the device's ``peer_session`` (0: not known yet), MAC-tagged."""
    w = [float(v) for v in wrench]
    _check_dim(len(w))
    _finite(w, 'wrench')
    if int(flags) & ~_COMMAND_FLAGS:
        raise ProtocolError(Malformed.FIELD, f'unknown command flags {int(flags):#x}')
    if not 1 <= ttl_us < 2**32:
        raise ProtocolError(Malformed.FIELD, f'ttl_us must be in [1, 2^32 - 1], got {ttl_us}')
    head = _header_fields(PacketType.COMMAND, int(flags), len(w), session, seq, stamp_ns,
                          echo_seq, echo_stamp_ns, key)
    return _seal(_COMMAND_STRUCTS[len(w)], (*head, ttl_us, *w), key, peer_session)


def encode_state(session: int, seq: int, stamp_ns: int, echo_seq: int, echo_stamp_ns: int,
                 status: int, applied_seq: int, pose: Sequence[float] | np.ndarray,
                 twist: Sequence[float] | np.ndarray, hand_wrench: Sequence[float] | np.ndarray,
                 applied_wrench: Sequence[float] | np.ndarray, key: LinkKey | None = None,
                 peer_session: int = 0) -> bytes:
    """A STATE datagram; refuses (:class:`ProtocolError`) non-finite values, vectors of
    unequal or wrong size, unknown status bits, out-of-range integers. With ``key``: version
    2, addressed to the client's ``peer_session`` (0: a monitor copy), MAC-tagged."""
    vectors = [[float(v) for v in vec] for vec in (pose, twist, hand_wrench, applied_wrench)]
    m = len(vectors[0])
    _check_dim(m)
    names = ('pose', 'twist', 'hand_wrench', 'applied_wrench')
    for name, vec in zip(names, vectors, strict=True):
        if len(vec) != m:
            raise ProtocolError(Malformed.SIZE, f'{name} must have {m} values, got {len(vec)}')
        _finite(vec, name)
    if int(status) & ~STATUS_MASK or int(status) < 0:
        raise ProtocolError(Malformed.FIELD, f'unknown status bits {int(status):#x} (known '
                            f'{STATUS_MASK:#x})')
    _check_u64('applied_seq', applied_seq)
    head = _header_fields(PacketType.STATE, 0, m, session, seq, stamp_ns, echo_seq,
                          echo_stamp_ns, key)
    return _seal(_STATE_STRUCTS[m], (*head, int(status), applied_seq, *vectors[0],
                                     *vectors[1], *vectors[2], *vectors[3]), key, peer_session)


def _verify(data: bytes | bytearray | memoryview, n: int, key: LinkKey) -> int:
    """Check the tag of an authenticated datagram before anything of it is read; its
    ``peer_session``. Only to name the refusal are magic, version and key id looked at."""
    if n < HEADER.size + TRAILER[True]:
        raise ProtocolError(Malformed.SIZE, f'datagram of {n} bytes: shorter than a header and '
                            f'an authenticated trailer ({HEADER.size + TRAILER[True]} bytes)')
    view = memoryview(data)
    if hmac.compare_digest(key.tag(view[:n - TAG_SIZE]), view[n - TAG_SIZE:n]):
        return int(_AUTH.unpack_from(data, n - TRAILER[True])[0])
    if bytes(view[:4]) == MAGIC and view[4] == VERSION:
        raise ProtocolError(Rejected.UNAUTHENTICATED, 'an unauthenticated (version 1) packet: '
                            'this receiver has a key and takes only authenticated ones')
    key_id = _AUTH.unpack_from(data, n - TRAILER[True])[1]
    if key_id != key.key_id:
        raise ProtocolError(Rejected.WRONG_KEY, f'made with key id {key_id:08x}, this '
                            f'receiver\'s key is {key.key_id:08x}: another key')
    raise ProtocolError(Rejected.MAC, 'the MAC does not match the contents: forged or '
                        'corrupted')


def decode(data: bytes | bytearray | memoryview, m: int | None = None,
           expect: PacketType | None = None, key: LinkKey | None = None) -> Command | State:
    """The packet in ``data``; ``m``: the receiver's task dimension (None: any of 3, 6);
    ``expect``: the only type the receiver takes (None: both); ``key``: the link's key (then
    only authenticated packets, the MAC verified first). Raises :class:`ProtocolError`
    naming what is wrong (module doc, "Refused packets", "Authenticated link")."""
    n = len(data)
    auth = key is not None
    peer = 0
    if key is not None:
        peer = _verify(data, n, key)
    elif n < HEADER.size + _CRC.size:
        raise ProtocolError(Malformed.SIZE, f'datagram of {n} bytes: shorter than a header '
                            f'and CRC ({HEADER.size + _CRC.size} bytes)')
    (magic, version, ptype_raw, flags, dim, session, seq, stamp_ns, echo_seq,
     echo_stamp_ns) = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(Malformed.MAGIC, f'magic {bytes(magic)!r}, expected {MAGIC!r}')
    want_version = VERSION_AUTH if auth else VERSION
    if version != want_version:
        hint = (': an authenticated packet, but this receiver has no key (key_file / '
                '--key-file)' if version == VERSION_AUTH else '')
        raise ProtocolError(Malformed.VERSION, f'protocol version {version}, expected '
                            f'{want_version}{hint}')
    if ptype_raw not in (1, 2):
        raise ProtocolError(Malformed.TYPE, f'packet type {ptype_raw}, expected 1 (COMMAND) '
                            'or 2 (STATE)')
    ptype = PacketType(ptype_raw)
    if expect is not None and ptype is not expect:
        raise ProtocolError(Malformed.TYPE, f'packet type {ptype.name}, expected '
                            f'{expect.name} here')
    if dim not in DIMS or (m is not None and dim != m):
        want = f'{m}' if m is not None else '3 or 6'
        raise ProtocolError(Malformed.DIM, f'task dimension m = {dim}, expected {want}')
    size = packet_size(ptype, dim, auth)
    if n != size:
        raise ProtocolError(Malformed.SIZE, f'{ptype.name} of m = {dim} must be {size} bytes, '
                            f'got {n}')
    if not auth:
        crc = zlib.crc32(memoryview(data)[:n - _CRC.size])
        (sent_crc,) = _CRC.unpack_from(data, n - _CRC.size)
        if crc != sent_crc:
            raise ProtocolError(Malformed.CRC, f'CRC32 {sent_crc:#010x} does not match the '
                                f'contents ({crc:#010x}): corrupted')
    if session == 0 or seq == 0:
        raise ProtocolError(Malformed.FIELD, f'session {session} and seq {seq} must be >= 1')
    if ptype is PacketType.COMMAND:
        fields = _COMMAND_STRUCTS[dim].unpack_from(data)
        if flags & ~_COMMAND_FLAGS:
            raise ProtocolError(Malformed.FIELD, f'unknown command flags {flags:#x}')
        ttl_us = fields[10]
        if ttl_us == 0:
            raise ProtocolError(Malformed.FIELD, 'ttl_us must be >= 1, got 0')
        wrench = fields[11:]
        _finite(wrench, 'wrench')
        return Command(session, seq, stamp_ns, echo_seq, echo_stamp_ns, CommandFlags(flags),
                       ttl_us, np.array(wrench), peer)
    fields = _STATE_STRUCTS[dim].unpack_from(data)
    if flags:
        raise ProtocolError(Malformed.FIELD, f'STATE flags must be 0, got {flags:#x}')
    status, applied_seq = fields[10], fields[11]
    if status & ~STATUS_MASK:
        raise ProtocolError(Malformed.FIELD, f'unknown status bits {status & ~STATUS_MASK:#x}')
    values = fields[12:]
    _finite(values, 'state values')
    a = np.array(values)
    return State(session, seq, stamp_ns, echo_seq, echo_stamp_ns, status, applied_seq,
                 a[:dim], a[dim:2 * dim], a[2 * dim:3 * dim], a[3 * dim:], peer)


# -- receiving: sequence numbers and sessions ----------------------------------------------------
class Arrival(enum.Enum):
    """What a valid packet's ``seq`` is, against the newest of its session."""

    NEW = 'new'
    DUPLICATE = 'duplicate'
    LATE = 'late'
    TOO_OLD = 'too_old'


class SeqTracker:
    """Classifies the seqs of one sender session (module doc, "Sequence numbers"); counts
    ``new``, ``duplicate``, ``late``, ``too_old`` and ``lost`` (seqs skipped and not arrived
    since; a late arrival within the window takes one off). ``window`` seqs behind the newest
    are remembered (a Python int as bit set: bit i = newest - i arrived)."""

    WINDOW = 1024

    def __init__(self, window: int = WINDOW) -> None:
        if window < 1:
            raise ValueError(f'window must be >= 1, got {window}')
        self.window = window
        self._full = (1 << window) - 1
        self.newest = 0
        self._seen = 0
        self.new = 0
        self.duplicate = 0
        self.late = 0
        self.too_old = 0
        self.lost = 0

    def arrive(self, seq: int) -> Arrival:
        """Classify ``seq`` (>= 1) and count it."""
        newest = self.newest
        if seq > newest:
            gap = seq - newest
            self.lost += gap - 1
            self._seen = ((self._seen << gap) | 1) & self._full if gap < self.window else 1
            self.newest = seq
            self.new += 1
            return Arrival.NEW
        back = newest - seq
        if back >= self.window:
            self.too_old += 1
            return Arrival.TOO_OLD
        bit = 1 << back
        if self._seen & bit:
            self.duplicate += 1
            return Arrival.DUPLICATE
        self._seen |= bit
        self.late += 1
        self.lost -= 1
        return Arrival.LATE


class SessionVerdict(enum.Enum):
    """What :meth:`SessionFollower.check` says of a packet's session."""

    CURRENT = 'current'
    NEW = 'new'            # the first session, or a new one that took over (restarted peer)
    FOREIGN = 'foreign'    # another session while the followed one is alive: refused
    ENDED = 'ended'        # a session that ended (released): refused


class SessionFollower:
    """The peer session a receiver follows. The first session is followed; another session
    takes over once the followed one has been silent ``takeover_after`` s (a restarted peer
    draws a new session id), else its packets are refused (``foreign``). A session that
    ended (:meth:`end`) is never followed again (``ended``). Each followed session has its own
    :class:`SeqTracker`; the counts of earlier sessions are kept in ``previous``.

    ``remember_all`` (an authenticated link): every session followed and left behind (ended,
    or taken over by a newer one) is kept in ``retired`` and never followed again, so a
    recorded packet of an earlier session is refused whenever it comes (its packets are
    counted in ``ended``; the receiver counts them as replays)."""

    _ENDED_KEPT = 16

    def __init__(self, takeover_after: float, remember_all: bool = False) -> None:
        if not takeover_after > 0.0:
            raise ValueError(f'takeover_after must be > 0 s, got {takeover_after}')
        self.takeover_after = takeover_after
        self.remember_all = remember_all
        #: Sessions left behind (``remember_all``): never followed again.
        self.retired: set[int] = set()
        self.session = 0
        self.tracker = SeqTracker()
        self.previous = SeqTracker()   # counters summed over the sessions before this one
        self.heard = -math.inf
        self.sessions = 0              # sessions followed so far
        self.foreign = 0
        self.ended_packets = 0
        self._ended: list[int] = []

    def check(self, session: int, now: float) -> SessionVerdict:
        """Whether to take a valid packet of ``session`` arrived at ``now`` (s); switches to a
        new session when it may take over (counted in ``sessions``)."""
        if session == self.session:
            return SessionVerdict.CURRENT
        if session in self._ended or session in self.retired:
            self.ended_packets += 1
            return SessionVerdict.ENDED
        if self.session and now - self.heard < self.takeover_after:
            self.foreign += 1
            return SessionVerdict.FOREIGN
        self._retire()
        self.session = session
        self.sessions += 1
        return SessionVerdict.NEW

    def heard_from(self, now: float) -> None:
        """A packet of the followed session was taken at ``now`` (s)."""
        self.heard = now

    def take(self, session: int, seq: int, now: float) -> SessionVerdict | None:
        """Whether a valid packet (``session``, ``seq``) arrived at ``now`` (s) is taken:
        :meth:`check`, then the session's :class:`SeqTracker` (only a seq newer than every
        one taken); ``CURRENT`` or ``NEW`` (a new session followed: the receiver resets what
        it held of the old one) when taken, None when refused (counted)."""
        verdict = self.check(session, now)
        if verdict is SessionVerdict.FOREIGN or verdict is SessionVerdict.ENDED:
            return None
        if self.tracker.arrive(seq) is not Arrival.NEW:   # a new session's first is NEW
            return None
        self.heard = now
        return verdict

    def end(self) -> None:
        """The followed session ended (released): forget it, refuse its packets from now."""
        if self.session:
            self._ended.append(self.session)
            del self._ended[:-self._ENDED_KEPT]
        self._retire()
        self.session = 0
        self.heard = -math.inf

    def _retire(self) -> None:
        if self.remember_all and self.session:
            self.retired.add(self.session)
        t, p = self.tracker, self.previous
        p.new += t.new
        p.duplicate += t.duplicate
        p.late += t.late
        p.too_old += t.too_old
        p.lost += t.lost
        self.tracker = SeqTracker()

    def totals(self) -> dict[str, int]:
        """Counts over every session: new, duplicate, late, too_old, lost, foreign, ended."""
        t, p = self.tracker, self.previous
        return {'new': t.new + p.new, 'duplicate': t.duplicate + p.duplicate,
                'late': t.late + p.late, 'too_old': t.too_old + p.too_old,
                'lost': t.lost + p.lost, 'foreign': self.foreign,
                'ended_session': self.ended_packets}


class MalformedCounts:
    """Refused datagrams per :class:`Malformed` and :class:`Rejected` reason, and the newest
    message of each."""

    def __init__(self) -> None:
        self.counts: dict[Malformed | Rejected, int] = dict.fromkeys([*Malformed, *Rejected], 0)
        self.last: dict[Malformed | Rejected, str] = {}

    def add(self, err: ProtocolError) -> None:
        self.counts[err.reason] += 1
        self.last[err.reason] = str(err)

    def reject(self, reason: Rejected, message: str) -> None:
        """Count a refusal found after decoding (a replay)."""
        self.counts[reason] += 1
        self.last[reason] = message

    @property
    def total(self) -> int:
        """Malformed datagrams (every :class:`Malformed` reason)."""
        return sum(n for r, n in self.counts.items() if isinstance(r, Malformed))

    @property
    def rejected(self) -> int:
        """Datagrams refused by the authenticated link (every :class:`Rejected` reason)."""
        return sum(n for r, n in self.counts.items() if isinstance(r, Rejected))

    def values(self, prefix: str = 'malformed_') -> dict[str, int]:
        """``{prefix + reason: count}`` for every :class:`Malformed` reason and
        ``{'rejected_' + reason: count}`` for every :class:`Rejected` one."""
        return {f'{prefix if isinstance(r, Malformed) else "rejected_"}{r.value}': n
                for r, n in self.counts.items()}
