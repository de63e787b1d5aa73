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


class AxesError(ConfigError):
    """A scenario's task needs a device axis (a force along or torque about a world axis) that
    the device backend does not actuate or sense: refused at configure, before anything moves
    (``haptic-topology`` exits with status 2)."""


class BagError(HapticTopologyError):
    """A bag is missing, corrupt, truncated or holds unexpected message types."""


class BagWriteError(BagError, OSError):
    """A bag's file could not be written (disk full, I/O error): raised by
    ``haptic_topology.bag.writer.BagWriter``'s ``flush`` and ``close``, naming the file;
    an ``OSError`` too (``errno`` set), so code catching ``OSError`` catches it. What was
    flushed before stays readable (``haptic-topology bag repair``)."""

    def __init__(self, message: str, errno: int | None = None) -> None:
        super().__init__(message)
        self.errno = errno


class DeviceError(HapticTopologyError):
    """A device backend cannot be configured, activated, read or written."""


class VendorLibraryMissing(DeviceError, ConfigError):
    """A vendor backend's Python package or the vendor's own library cannot be loaded: one line
    naming the package, the library and the environment variable that points to it
    (``haptic-topology`` exits with status 2, as for a configuration error). ``detail``: what
    the loader said, appended."""

    def __init__(self, backend: str, package: str, library: str, variable: str,
                 detail: str = '') -> None:
        self.backend, self.package, self.library = backend, package, library
        self.variable, self.detail = variable, detail
        more = f' ({detail})' if detail else ''
        super().__init__(f'{backend}: cannot load {library} through the Python package '
                         f'{package}{more}; install both and set {variable} '
                         f'(docs/devices.md)')

    def __reduce__(self) -> tuple[object, ...]:     # pickled across processes whole
        return (type(self), (self.backend, self.package, self.library, self.variable,
                             self.detail))


class TruncatedError(BagError):
    """The MCAP stream ended before its footer (the bag's readers keep what came before)."""


class ReplayError(HapticTopologyError):
    """The replay could not run (no subscriber, controller failed to start, ...)."""


class MessageError(HapticTopologyError):
    """An incoming message does not fit the graph (sizes, task_dim, non-finite values,
    integers out of range); ``reason`` is one of
    ``haptic_topology.messages.check.REASONS``."""

    def __init__(self, reason: str, text: str) -> None:
        super().__init__(text)
        self.reason = reason


class MessageDefinitionError(HapticTopologyError):
    """The .msg files of haptic_topology_msgs cannot be found or parsed."""


class LinkError(HapticTopologyError):
    """An interface cannot be opened, or the bridge lacks the privilege to open it."""


class WaitTimeout(HapticTopologyError):
    """Something the graph should have done within a deadline did not happen."""


class TransitionRefused(WaitTimeout):
    """A lifecycle node answered a transition (configure, activate, ...) with failure: its
    reason is in its ``/diagnostics`` status, at ERROR."""


class BringupError(HapticTopologyError):
    """A node of the graph failed to start, or the loop never closed."""


class SimulationError(HapticTopologyError):
    """The virtual environment's state left what it can model (e.g. it is no longer finite:
    the integration diverged)."""


def error_line(exc: BaseException, where: str) -> str:
    """The one line reported for ``exc``, raised in ``where`` (e.g. ``'network: activate()'``):
    a package error's own message (it names what it received and what it expected), else
    ``<where> raised <type>: <text>`` (a bug in code of another's, such as a device
    backend's)."""
    if isinstance(exc, HapticTopologyError):
        return str(exc)
    return f'{where} raised {type(exc).__name__}: {exc}'
