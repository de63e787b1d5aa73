"""Device backends: the seam between ``device_driver`` and a haptic device (real or simulated).

A backend is one class derived from :class:`DeviceBackend`, modelled on ros2_control's
``SystemInterface``: a lifecycle (:meth:`~DeviceBackend.configure` ->
:meth:`~DeviceBackend.activate` -> cycles -> :meth:`~DeviceBackend.deactivate`) and, once per
device cycle, :meth:`~DeviceBackend.write` of the control wrench ``u`` followed by
:meth:`~DeviceBackend.read` of the device state after ``dt`` seconds. The driver clamps ``u``
to the configured limits before ``write`` and owns timing, sequence numbers, the watchdog and
all ROS I/O; a backend does no ROS.

Backends are selected by name (the ``backend`` parameter of ``device_driver``):

* a built-in name: ``sim_maglev`` (:class:`SimMaglevBackend`), ``hardware``
  (:class:`HardwareBackend`, a stub that explains what to implement);
* ``package.module:ClassName``: any importable subclass of :class:`DeviceBackend`;
* a name registered by an installed distribution in the entry point group
  ``haptic_topology.device_backends`` (``name = package.module:ClassName``).

So a new device is one class, and nothing else in the graph changes.
"""

from __future__ import annotations

import importlib
import importlib.metadata as md
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from haptic_topology.device.maglev import DeviceParams, DeviceStatus, MaglevModel, PositionSensor
from haptic_topology.device.users import UserModel, user_from_config
from haptic_topology.errors import DeviceError

#: Entry point group through which other distributions can add backends.
ENTRY_POINT_GROUP = 'haptic_topology.device_backends'


@dataclass(frozen=True)
class BackendConfig:
    """What a backend is configured with (task vectors of length m = ``params.task.dim``).

    ``params``: device model and limits from the scenario; ``initial_pose``: where a simulated
    device starts (a real device ignores it); ``user``: the scenario's simulated-user mapping;
    ``options``: backend-specific settings (the driver's ``backend_options`` parameter, YAML).
    """

    params: DeviceParams
    initial_pose: np.ndarray
    user: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)
    source: str = ''


@dataclass(frozen=True)
class DeviceReading:
    """One sample of the device: pose, twist, measured hand wrench ``F_h``, status bits."""

    pose: np.ndarray
    twist: np.ndarray
    hand_wrench: np.ndarray
    status: DeviceStatus = DeviceStatus.OK


class DeviceBackend(ABC):
    """A haptic device as seen by ``device_driver`` (one instance per driver).

    Lifecycle: ``configure`` once, then ``activate``; the driver then calls ``write(u)`` and
    ``read(dt)`` once per cycle (or ``idle(dt)`` while no controller has engaged), and
    ``deactivate`` on shutdown (also after a failed ``activate``). Errors are raised as
    :class:`~haptic_topology.errors.DeviceError` with a message for the operator.
    """

    #: Name used in logs and diagnostics.
    name: ClassVar[str] = 'backend'

    @abstractmethod
    def configure(self, config: BackendConfig) -> None:
        """Take the configuration; check options; do not move anything yet."""

    @abstractmethod
    def activate(self) -> None:
        """Open the device and enable its output (amplifiers on, levitation, ...)."""

    @abstractmethod
    def deactivate(self) -> None:
        """Command zero wrench and release the device; must be safe to call more than once."""

    @abstractmethod
    def write(self, wrench: np.ndarray) -> None:
        """Set the control wrench ``u`` (N, N m; already clamped) for the coming cycle."""

    @abstractmethod
    def read(self, dt: float) -> DeviceReading:
        """The device state ``dt`` s (measured) after the previous read."""

    def idle(self, dt: float) -> DeviceReading:
        """A cycle before any controller engaged: zero wrench. Simulations may park instead."""
        self.write(np.zeros(self.task_dim()))
        return self.read(dt)

    def task_dim(self) -> int:
        """m of the task vectors (3 planar, 6 spatial); valid after ``configure``."""
        raise DeviceError(f'{type(self).__name__} does not implement task_dim()')


class SimMaglevBackend(DeviceBackend):
    """The simulated maglev of the paper's lab (eq. 9, :class:`MaglevModel`) with the
    scenario's simulated user.

    Until the first :meth:`write` from an engaged controller the model is parked at its
    initial pose (``idle`` does not integrate), so a run starts when the loop is closed, like
    the offline lock-step simulation. The user's clock starts at engagement too. What it
    reports goes through the scenario's sensor model (:class:`PositionSensor`: exact unless
    ``device.sensor`` says otherwise); the simulated user feels the true state.
    Options: none.
    """

    name = 'sim_maglev'

    def __init__(self) -> None:
        self._model: MaglevModel | None = None
        self._sensor: PositionSensor | None = None
        self._user: UserModel | None = None
        self._u = np.zeros(0)
        self._f_h = np.zeros(0)
        self._t = 0.0
        self._active = False

    def configure(self, config: BackendConfig) -> None:
        if config.options:
            raise DeviceError(f'{self.name}: backend_options: expected none, got '
                              f'{sorted(config.options)}')
        p = config.params
        self._model = MaglevModel(p, config.initial_pose)
        self._sensor = PositionSensor(p)
        self._user = user_from_config(config.user, p.task, f'{config.source}: scenario.user',
                                      self._model.pose)
        m = p.task.dim
        self._u = np.zeros(m)
        self._t = 0.0
        self._f_h = self._user.wrench(0.0, self._model.pose, self._model.twist)

    def _require(self) -> tuple[MaglevModel, UserModel]:
        if self._model is None or self._user is None:
            raise DeviceError(f'{self.name}: used before configure()')
        return self._model, self._user

    def _reading(self, dt: float, status: DeviceStatus = DeviceStatus.OK) -> DeviceReading:
        model, _ = self._require()
        assert self._sensor is not None
        pose, twist = self._sensor.measure(model.pose, model.twist, dt)
        return DeviceReading(pose, twist, self._f_h.copy(), status)

    def task_dim(self) -> int:
        return self._require()[0].params.task.dim

    def activate(self) -> None:
        self._require()
        self._active = True

    def deactivate(self) -> None:
        self._active = False
        self._u = np.zeros_like(self._u)

    def write(self, wrench: np.ndarray) -> None:
        self._u = np.array(wrench, dtype=float)

    def read(self, dt: float) -> DeviceReading:
        model, user = self._require()
        if not self._active:
            raise DeviceError(f'{self.name}: read() before activate()')
        status = model.step(self._u, self._f_h, dt)
        self._t += dt
        self._f_h = user.wrench(self._t, model.pose, model.twist)
        return self._reading(dt, status)

    def idle(self, dt: float) -> DeviceReading:
        return self._reading(dt)


class HardwareBackend(DeviceBackend):
    """Placeholder for a real device; refuses to activate and says what to implement."""

    name = 'hardware'

    def configure(self, config: BackendConfig) -> None:
        self._m = config.params.task.dim

    def task_dim(self) -> int:
        return self._m

    def activate(self) -> None:
        raise DeviceError(
            'backend hardware: no device driver is implemented in this package. To drive a '
            'real device, write a subclass of haptic_topology.device.backend.DeviceBackend '
            'implementing configure() (open/validate your connection from backend_options), '
            'activate() (enable the output), write(u) (send the wrench, N and N m, task frame), '
            'read(dt) (return pose, twist and measured hand wrench as DeviceReading) and '
            'deactivate() (zero the output), then select it with the parameter '
            "backend:='your.module:YourBackend' or register it in the entry point group "
            f'{ENTRY_POINT_GROUP}.')

    def deactivate(self) -> None:
        pass

    def write(self, wrench: np.ndarray) -> None:
        raise DeviceError('backend hardware: not implemented (see activate())')

    def read(self, dt: float) -> DeviceReading:
        raise DeviceError('backend hardware: not implemented (see activate())')


#: Built-in backends by name.
BUILTIN_BACKENDS: dict[str, type[DeviceBackend]] = {
    SimMaglevBackend.name: SimMaglevBackend,
    HardwareBackend.name: HardwareBackend,
}


def zero_and_release(backend: DeviceBackend, dim: int) -> None:
    """Write a zero wrench (``dim`` components), then :meth:`DeviceBackend.deactivate`: the
    end of every active period (a device that refuses the write is released all the
    same)."""
    try:
        backend.write(np.zeros(dim))
    except DeviceError:
        pass
    backend.deactivate()


def _import_class(spec: str) -> Any:
    module_name, _, attr = spec.partition(':')
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DeviceError(f'backend {spec!r}: cannot import module {module_name!r} ({exc})'
                          ) from None
    try:
        return getattr(module, attr)
    except AttributeError:
        raise DeviceError(f'backend {spec!r}: module {module_name!r} has no {attr!r}') from None


def backend_class(name: str) -> type[DeviceBackend]:
    """Resolve a backend name (built-in, ``module:Class`` or entry point; see module doc)."""
    if name in BUILTIN_BACKENDS:
        cls: Any = BUILTIN_BACKENDS[name]
    elif ':' in name:
        cls = _import_class(name)
    else:
        eps = [ep for ep in md.entry_points(group=ENTRY_POINT_GROUP) if ep.name == name]
        if not eps:
            known = sorted(BUILTIN_BACKENDS) + sorted(
                ep.name for ep in md.entry_points(group=ENTRY_POINT_GROUP))
            raise DeviceError(f'backend {name!r}: unknown; expected one of {", ".join(known)} '
                              'or module:Class')
        cls = eps[0].load()
    if not (isinstance(cls, type) and issubclass(cls, DeviceBackend)):
        raise DeviceError(f'backend {name!r}: {cls!r} is not a subclass of DeviceBackend')
    return cls


def create_backend(name: str) -> DeviceBackend:
    """An unconfigured instance of the backend called ``name``."""
    return backend_class(name)()
