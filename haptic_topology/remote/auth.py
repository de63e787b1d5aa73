"""The pre-shared key of an authenticated device link, and when a link must have one.

The device protocol (:mod:`haptic_topology.remote.protocol`) carries, when both sides have a
key, a keyed MAC on every packet: BLAKE2b (RFC 7693) in its keyed mode with a 16-byte tag,
from the standard library's ``hashlib``. BLAKE2b is a MAC by itself when given a key (no
HMAC construction around it) and costs about a fifth of HMAC-SHA256 per packet in CPython,
which matters on the driver's 1 kHz deadline path.

**The key file** holds the key as hexadecimal text (32 to 64 bytes, so 64 to 128 hex digits;
white space around it ignored). It is refused unless only its owner may read or write it
(mode ``0600`` or ``0400``, as ``ssh`` refuses a private key): a key that others can read
authenticates nothing. Make one with ``haptic-topology device-key PATH`` or::

    (umask 077; python3 -c 'import secrets; print(secrets.token_hex(32))' > PATH)

**Key id.** Each packet also carries a 4-byte id of the key (a BLAKE2b digest of the key under
its own personalisation string: it says nothing usable about the key), so that a peer
configured with another key is told apart from a forged or corrupted packet
(``rejected_wrong_key`` vs ``rejected_mac``).

**Loopback or key.** :func:`require_key_off_loopback`: a device link on an address other than
loopback without a key is refused unless the user says the network is trusted
(``--trusted-network``, backend option ``trusted_network: true``).
"""

from __future__ import annotations

import hashlib
import ipaddress
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

from haptic_topology.errors import ConfigError

#: Bytes of the MAC tag at the end of an authenticated packet.
TAG_SIZE = 16
#: The MAC's name in summaries and diagnostics.
ALGORITHM = 'BLAKE2b-128'
KEY_MIN, KEY_MAX = 32, 64
_KEY_ID_PERSON = b'HTDP key id'


def key_id_of(key: bytes) -> int:
    """The 4-byte id of ``key`` (uint32, little-endian of a 4-byte BLAKE2b digest of the key
    with personalisation ``b'HTDP key id'``)."""
    return int.from_bytes(hashlib.blake2b(key, digest_size=4, person=_KEY_ID_PERSON).digest(),
                          'little')


@dataclass(frozen=True)
class LinkKey:
    """A pre-shared key (32 to 64 bytes) and its id; :meth:`tag` is the MAC."""

    key: bytes = field(repr=False)
    source: str = ''

    def __post_init__(self) -> None:
        if not KEY_MIN <= len(self.key) <= KEY_MAX:
            raise ConfigError(f'device link key{self._where}: must be {KEY_MIN} to {KEY_MAX} '
                              f'bytes ({2 * KEY_MIN} to {2 * KEY_MAX} hex digits), got '
                              f'{len(self.key)} bytes')
        object.__setattr__(self, 'key_id', key_id_of(self.key))

    key_id: int = field(init=False, default=0)

    @property
    def _where(self) -> str:
        return f' {self.source}' if self.source else ''

    def tag(self, data: bytes | bytearray | memoryview) -> bytes:
        """The 16-byte MAC of ``data``: ``hashlib.blake2b(data, key=key, digest_size=16)``."""
        return hashlib.blake2b(data, key=self.key, digest_size=TAG_SIZE).digest()

    def describe(self) -> str:
        """``'authenticated (BLAKE2b-128, key id 1a2b3c4d)'``."""
        return f'authenticated ({ALGORITHM}, key id {self.key_id:08x})'


def load_key(path: str | os.PathLike[str]) -> LinkKey:
    """The key in the file ``path`` (module doc); :class:`~haptic_topology.errors.ConfigError`
    naming the file when it is missing, readable or writable by others than its owner, or
    not 32 to 64 bytes of hex."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError as exc:
        raise ConfigError(f'device link key file {p}: cannot read it ({exc.strerror})'
                          ) from None
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(f'device link key file {p}: not a regular file')
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        raise ConfigError(f'device link key file {p}: mode {mode:04o} lets others than its '
                          f'owner read or write it; expected 0600 or 0400 (chmod 600 {p})')
    try:
        text = p.read_text(encoding='ascii').strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f'device link key file {p}: cannot read it ({exc})') from None
    try:
        key = bytes.fromhex(text)
    except ValueError:
        raise ConfigError(f'device link key file {p}: expected the key as hexadecimal text '
                          f'({2 * KEY_MIN} to {2 * KEY_MAX} hex digits)') from None
    return LinkKey(key, str(p))


def write_key(path: str | os.PathLike[str]) -> LinkKey:
    """A new random 32-byte key written to ``path`` (mode 0600, refused if it exists)."""
    import secrets

    p = Path(path)
    key = secrets.token_bytes(KEY_MIN)
    try:
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise ConfigError(f'device link key file {p}: cannot create it ({exc.strerror})'
                          ) from None
    with os.fdopen(fd, 'w', encoding='ascii') as f:
        f.write(key.hex() + '\n')
    return LinkKey(key, str(p))


def is_loopback(ip: str) -> bool:
    """Whether the numeric address ``ip`` is a loopback address (``127.0.0.0/8``, ``::1``,
    IPv4-mapped loopback); a wildcard (``0.0.0.0``, ``::``) is not."""
    try:
        addr = ipaddress.ip_address(ip.split('%', 1)[0])
    except ValueError:
        return False
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        return addr.ipv4_mapped.is_loopback
    return addr.is_loopback


def link_mode(key: LinkKey | None, trusted_network: bool) -> str:
    """What a summary says of the link: :meth:`LinkKey.describe`, ``'unauthenticated
    (trusted network)'`` or ``'unauthenticated (loopback)'``."""
    if key is not None:
        return key.describe()
    return 'unauthenticated (trusted network)' if trusted_network else \
        'unauthenticated (loopback)'


def require_key_off_loopback(who: str, ip: str, key: LinkKey | None, trusted_network: bool,
                             key_option: str, trusted_option: str) -> None:
    """Refuse (:class:`~haptic_topology.errors.ConfigError`) a link on the non-loopback
    address ``ip`` with no key, unless ``trusted_network``; the message names the options
    that fix it."""
    if key is None and not trusted_network and not is_loopback(ip):
        raise ConfigError(
            f'{who}: {ip} is not a loopback address and no key is configured: any host that '
            f'can reach it could move the device or read its state. Give {key_option} (a '
            f'pre-shared key, docs/devices.md "Authenticated link") or {trusted_option} if '
            'this network is trusted')
