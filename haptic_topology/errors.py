"""Exception hierarchy of haptic_topology: one base class, one subclass per kind of fault.

Callers catch :class:`HapticTopologyError` (or a subclass) and print ``str(err)``; every message
names the offending field, file or value and what was expected.
"""

from __future__ import annotations


class HapticTopologyError(Exception):
    """Base class of every error raised by this package."""


class ConfigError(HapticTopologyError):
    """A configuration file or value is missing, malformed or out of range."""


class LinkageError(ConfigError):
    """A linkage description (YAML or URDF) fails validation."""


class BagError(HapticTopologyError):
    """A bag is missing, corrupt, truncated or holds unexpected message types."""


class DeviceError(HapticTopologyError):
    """A device backend cannot be configured, activated, read or written."""
