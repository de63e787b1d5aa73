"""Device backends: the seam between ``device_driver`` and a haptic device (real or simulated).

(One module of ~505 lines on purpose: the backend contract, the registry and the simulated
maglev that every other backend is checked against belong together.)

A backend is one class derived from :class:`DeviceBackend`, modelled on ros2_control's
``SystemInterface``: a lifecycle (:meth:`~DeviceBackend.configure` ->
:meth:`~DeviceBackend.activate` -> cycles -> :meth:`~DeviceBackend.deactivate`) and, once per
device cycle, :meth:`~DeviceBackend.write` of the control wrench ``u`` followed by
:meth:`~DeviceBackend.read` of the device state after ``dt`` seconds. The driver clamps ``u``
to the configured limits before ``write`` and owns timing, sequence numbers, the watchdog and
all ROS I/O; a backend does no ROS.

Backends are selected by name (the ``backend`` parameter of ``device_driver``):

* a built-in name (:data:`BUILTIN_BACKENDS`): ``sim_maglev`` (:class:`SimMaglevBackend`),
  ``ros_topics`` (``haptic_topology.nodes.topic_backend.RosTopicBackend``: a device with
  a ROS 2 driver, read from ``PoseStamped``/``TwistStamped`` and commanded with
  ``WrenchStamped``), ``network`` (:class:`~haptic_topology.remote.network.NetworkBackend`: a
  device controller on another computer, over UDP). The last two are imported only when
  selected (the ROS one needs rclpy, which the core never imports);
* ``package.module:ClassName``: any importable subclass of :class:`DeviceBackend`;
* a name registered by an installed distribution in the entry point group
  ``haptic_topology.device_backends`` (``name = package.module:ClassName``; a complete
  example distribution is ``examples/my_device_backend``).

So a new device is one class, and nothing else in the graph changes. What every backend
must do (clamped wrenches only reach the device, a non-finite wrench never does, zero on
``deactivate``, ``deactivate`` twice is harmless, ``activate`` again after it works, a fault
of the device is a status bit) is checked for each backend by the same tests
(``test/support/backend_conformance.py``).

**Faults.** A backend reports a fault of its device (amplifier fault, lost encoder, an
emergency stop pressed on the device, ...) by setting ``DeviceStatus.FAULT`` in the status
of what :meth:`~DeviceBackend.read` (or ``idle``) returns, for as long as the fault lasts, and
says why through :meth:`~DeviceBackend.fault_reason`. The driver then writes a zero wrench from
the next cycle on until a reading comes without the bit, and fades the output back in over
the watchdog ramp after it (:class:`~haptic_topology.device.loop.DeviceLoop`); the states carry
``STATUS_FAULT`` and ``/diagnostics`` is at ERROR with the reason and
:attr:`~DeviceBackend.hardware_id`. The wrench of the cycle in which the fault is first read
was written before the read: a device that faults must not apply force by itself.
"""

from __future__ import annotations

import importlib
import importlib.metadata as md
import pickle
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

import numpy as np

from haptic_topology.device.maglev import DeviceParams, MaglevModel, PositionSensor
from haptic_topology.device.users import UserModel, user_from_config
from haptic_topology.errors import AxesError, ConfigError, DeviceError, error_line
from haptic_topology.vocabulary import ALL_AXES, Axis, DeviceStatus, TaskSpace, axes_text

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


#: Task dimension -> its name in :attr:`DeviceBackend.hardware_id` of a backend that does not
#: say its task (:meth:`DeviceBackend.task`): only the dimensions one task has (2
#: planar_point, 6 spatial); m = 3 is planar or spatial_point.
_TASK_NAMES = {m: tasks[0].value for m in {t.dim for t in TaskSpace}
               if len(tasks := [t for t in TaskSpace if t.dim == m]) == 1}


@dataclass(frozen=True)
class DeviceAxes:
    """What a device senses and actuates, as world axes
    (:class:`~haptic_topology.vocabulary.Axis`: a translation x, y, z, or a rotation about
    one): ``sensed``, the axes whose motion it measures; ``actuated``, those along which it
    applies force or about which it applies torque. A 3-axis force device (most desktop
    devices) actuates x, y, z; a planar maglev x, y and rz; a 6-DOF maglev all six."""

    sensed: frozenset[Axis]
    actuated: frozenset[Axis]


#: A device that senses and actuates every axis (the simulated maglevs).
ALL_DEVICE_AXES = DeviceAxes(ALL_AXES, ALL_AXES)
#: A 3-axis force device: it senses and actuates translations only.
TRANSLATION_AXES = DeviceAxes(frozenset((Axis.X, Axis.Y, Axis.Z)),
                              frozenset((Axis.X, Axis.Y, Axis.Z)))


def check_axes(task: TaskSpace, axes: DeviceAxes, scenario: str, device: str,
               alternative: str | None = None) -> None:
    """Refuse (:class:`~haptic_topology.errors.AxesError`, one line naming both) a task that
    needs an axis the device does not actuate or sense
    (:attr:`~haptic_topology.vocabulary.TaskSpace.axes`): a torque
    the controller asks for would otherwise be dropped without a word. ``alternative``: what
    to use instead (e.g. the point-grasp scenario ``fig8_point``), added to the message.

    Example: ``scenario fig8 needs torque about z; device force3 actuates x, y, z forces
    only: use fig8_point``."""
    hint = f': use {alternative}' if alternative else ''
    for what, have in (('actuates', axes.actuated), ('senses', axes.sensed)):
        missing = [a for a in task.axes if a not in have]
        if missing:
            need = axes_text(frozenset(missing))
            raise AxesError(f'scenario {scenario} needs {need}; device {device} {what} '
                            f'{axes_text(have)} only{hint}')


class DeviceReading(NamedTuple):
    """One sample of the device: pose, twist, measured hand wrench ``F_h`` (task vectors, units
    of :mod:`haptic_topology.device.maglev`), status bits. ``status`` may carry
    ``WORKSPACE_LIMIT``, ``SATURATED`` and ``FAULT`` (the device reports a fault, see the
    module doc); the driver adds ``WATCHDOG`` and ``IDLE`` itself."""

    pose: np.ndarray
    twist: np.ndarray
    hand_wrench: np.ndarray
    status: DeviceStatus = DeviceStatus.OK


class DeviceBackend(ABC):
    """A haptic device as seen by ``device_driver`` (one instance per driver).

    Lifecycle (ros2_control's): ``configure`` once, then ``activate``; the driver then calls
    ``write(u)`` and ``read(dt)`` once per cycle (or ``idle(dt)`` while no controller has
    engaged), ``deactivate`` (also after a failed ``activate``; ``activate`` may follow), and
    ``cleanup`` on the lifecycle cleanup and at shutdown. Errors are raised as
    :class:`~haptic_topology.errors.DeviceError` with a message for the operator; a fault the
    device reports while running is a status bit instead (module doc, "Faults").
    """

    #: Name used in logs and diagnostics (the ``backend`` parameter's built-in name).
    name: ClassVar[str] = 'backend'
    #: Whether the device can follow the driver's simulated clock (``clock: lockstep``): it
    #: advances only when read, by the ``dt`` it is given. False for a device that runs on its
    #: own clock (a real one, a remote server): the driver refuses lock-step with it.
    lockstep: ClassVar[bool] = True
    #: Whether the backend uses rclpy itself (a node of its own in the driver's process): then
    #: it cannot run in the loop process (``loop_process``), which imports no rclpy.
    needs_ros: ClassVar[bool] = False
    #: Whether the device is a simulation (False: a real device, or one that may be).
    simulated: ClassVar[bool] = False
    #: Whether its velocity is a filtered difference of positions (OpenHaptics); ``passivity:
    #: auto`` then leaves the passivity controller off, as for a simulated device
    #: (:func:`haptic_topology.config.resolve.passivity_by_default`).
    velocity_filtered: ClassVar[bool] = False
    #: Whether the device's own servo loop is the loop's clock (OpenHaptics' scheduler): the
    #: loop process then runs each cycle inside its callback (:meth:`run_clocked`); it still
    #: serves ``read``/``write`` to a loop that paces itself (in-process layouts, conformance).
    drives_loop: ClassVar[bool] = False

    def run_clocked(self, period: float, cycle: Callable[[float], None],
                    between: Callable[[float], bool], keep_going: Callable[[], bool]) -> None:
        """A backend that :attr:`drives_loop`: run the loop on the device's servo clock until
        it stops. Each servo tick (``period`` s; a backend whose servo loop runs at another
        rate refuses it), inside the device's callback: ``cycle(now)`` (``now``: monotonic
        s; one loop cycle: ``write``, ``read``, the controller) with the device's frame open,
        then, once the frame has gone to the device, ``between(now)`` (the work between two
        cycles; False: stop). The calling thread waits meanwhile and calls ``keep_going()``
        every few tens of milliseconds (False: stop after the current tick). Returns once the
        callback has stopped; raises :class:`~haptic_topology.errors.DeviceError` when the
        servo loop stops by itself, and re-raises what ``cycle`` or ``between`` raised."""
        del period, cycle, between, keep_going
        raise DeviceError(f'{self.name}: run_clocked(): the device has no servo clock of its '
                          'own (drives_loop is False)')

    @classmethod
    def axes(cls, options: Mapping[str, Any]) -> DeviceAxes:
        """The axes the device senses and actuates (:class:`DeviceAxes`) with the backend
        options ``options`` (the driver's ``backend_options``, parsed). The driver refuses a
        scenario whose task needs an axis it lacks before it configures the backend
        (:func:`check_axes`). Default: every axis, i.e. whatever the task needs; a backend
        of a device that lacks axes (a 3-axis force device: :data:`TRANSLATION_AXES`) must
        override it."""
        del options
        return ALL_DEVICE_AXES

    def preflight(self, config: BackendConfig) -> None:
        """Whether the device can be reached, asked on a fresh instance by ``haptic-topology
        run`` in its own process before it starts any node, so that an unreachable device
        fails the run at once with its own one-line reason (a
        :class:`~haptic_topology.errors.DeviceError`) instead of after the graph's start.
        It must leave the device as it found it (never enable an output) and release
        whatever it opened. Default: nothing
        to check (a simulated device, or one whose check is its ``configure``)."""
        del config

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

    def written(self, wrench: np.ndarray) -> np.ndarray:
        """What the device was sent by the newest ``write(wrench)`` (task vector, N, N m; the
        states', bags' and traces' ``applied``), called right after it: ``wrench`` unless the
        device gets something else (zero while a vendor hand does not grasp, a fade)."""
        return wrench

    def cleanup(self) -> None:
        """Release what ``configure`` and ``activate`` acquired and ``deactivate`` kept (a
        connection, a ROS node): the driver's lifecycle cleanup and its shutdown, always after
        ``deactivate``. Default: nothing to release. Safe to call more than once; a
        ``configure`` may follow."""
        return None

    def carry_over(self) -> bytes | None:
        """After ``deactivate``: what the next activation must start from when it runs on a
        new instance in a new process (``device_driver``'s loop process opens the device anew
        on each activation), for :meth:`resume`. A simulated device returns its state (pose,
        twist, its clock), since a device that jumped back to its initial pose would not be
        the device the VE and the controller left; a real device keeps its state itself.
        Default: None (nothing to carry)."""
        return None

    def resume(self, carried: bytes) -> None:
        """Take what :meth:`carry_over` of the same backend, configured the same, returned
        (called after ``configure``, before ``activate``). Default: refuse."""
        raise DeviceError(f'{self.name}: resume(): this backend carries no state over')

    def idle(self, dt: float) -> DeviceReading:
        """A cycle before any controller engaged: zero wrench. Simulations may park instead."""
        self.write(np.zeros(self.task_dim()))
        return self.read(dt)

    _task: TaskSpace | None = None      # the task kept by keep_task

    def keep_task(self, config: BackendConfig) -> TaskSpace:
        """Keep and return ``config.params.task`` (:meth:`task`, :meth:`task_dim`): called by
        a backend's :meth:`configure` once its own checks have passed."""
        self._task = config.params.task
        return self._task

    def task_dim(self) -> int:
        """m of :meth:`task` (3 planar, 6 spatial, 2 planar_point, 3 spatial_point); before
        ``configure`` a DeviceError. A backend that does not :meth:`keep_task` overrides it."""
        task = self.task()
        if task is None:
            raise DeviceError(f'{self.name}: used before configure()')
        return task.dim

    def task(self) -> TaskSpace | None:
        """The task configured (:meth:`keep_task`), or None: before ``configure``, or a
        backend that does not keep it (m alone does not tell: 3 is planar or spatial_point)."""
        return self._task

    @property
    def hardware_id(self) -> str:
        """The device this backend drives, as ``DiagnosticStatus.hardware_id`` of the driver's
        diagnostics: ``'<name> <task>'`` once configured (e.g. ``'sim_maglev planar'``,
        ``'sim_maglev spatial_point'``; the task of ``task()``, else named from ``task_dim()``
        where one task has that m, else ``'<m>-dof'``), ``'<name>'`` before.
        A backend of a real device overrides it with what identifies the unit (model and
        serial number, port or address). Read from the diagnostics thread at 1 Hz, never in
        the device cycle: return text, do no I/O."""
        task = self.task()
        if task is not None:
            return f'{self.name} {task.value}'
        try:
            dim = self.task_dim()
        except DeviceError:
            return self.name
        return f'{self.name} {_TASK_NAMES.get(dim, f"{dim}-dof")}'

    def values(self) -> dict[str, str]:
        """The backend's own figures (counters, link round trip) as diagnostics key/values,
        added to the driver's status. Called from the diagnostics thread at 1 Hz, never in the
        device cycle: return what ``read``/``write`` counted, do no I/O. Default: none."""
        return {}

    def fault_reason(self) -> str:
        """Why the newest reading carries ``DeviceStatus.FAULT``, for the operator (the
        diagnostics message at ERROR). Called from the diagnostics thread at 1 Hz while a fault
        is active, never in the device cycle: return text kept by ``read``, do no I/O. Default:
        a generic text; a backend that knows the cause overrides it."""
        return f'{self.name}: the device reports a fault'


class SimMaglevBackend(DeviceBackend):
    """The simulated maglev of the paper's lab (eq. 9,
    :class:`~haptic_topology.device.maglev.MaglevModel`) with the
    scenario's simulated user.

    Until the first :meth:`write` from an engaged controller the model is parked at its
    initial pose (``idle`` does not integrate), so a run starts when the loop is closed, like
    the offline lock-step simulation. The user's clock starts at engagement too. What it
    reports goes through the scenario's sensor model
    (:class:`~haptic_topology.device.maglev.PositionSensor`: exact unless
    ``device.sensor`` says otherwise); the simulated user feels the true state.
    Options: none.
    """

    name = 'sim_maglev'
    simulated = True

    def __init__(self) -> None:      # axes(): every axis (the default), any task
        self._model: MaglevModel | None = None
        self._sensor: PositionSensor | None = None
        self._user: UserModel | None = None
        self._u = np.zeros(0)
        self._f_h = np.zeros(0)
        self._t = 0.0
        self._active = False
        self._applied = np.zeros(0)     # the newest step's saturated wrench; 0 while parked

    def configure(self, config: BackendConfig) -> None:
        if config.options:
            raise DeviceError(f'{self.name}: backend_options: expected none, got '
                              f'{sorted(config.options)}')
        p = config.params
        self._model = MaglevModel(p, config.initial_pose)
        outside = self._model.outside_workspace()
        if outside is not None:
            raise ConfigError(f'{config.source}: the device would start {outside} (the VT '
                              'hand at scenario.q0 plus device.offset): choose a q0 or an '
                              'offset inside it')
        self._sensor = PositionSensor(p)
        self._user = user_from_config(config.user, p.task, f'{config.source}: scenario.user',
                                      self._model.pose)
        m = p.task.dim
        self._u = np.zeros(m)
        self._applied = np.zeros(m)
        self._t = 0.0
        self._f_h = self._user.wrench(0.0, self._model.pose, self._model.twist)
        self.keep_task(config)          # hardware_id: 'sim_maglev <task>'

    def _require(self) -> tuple[MaglevModel, UserModel]:
        if self._model is None or self._user is None:
            raise DeviceError(f'{self.name}: used before configure()')
        return self._model, self._user

    def _reading(self, model: MaglevModel, dt: float,
                 status: DeviceStatus = DeviceStatus.OK) -> DeviceReading:
        assert self._sensor is not None
        pose, twist = self._sensor.measure(model.pose, model.twist, dt)
        return DeviceReading(pose, twist, self._f_h.copy(), status)

    def activate(self) -> None:
        self._require()
        self._active = True
        self._applied = np.zeros_like(self._u)

    def deactivate(self) -> None:
        self._active = False
        self._u = np.zeros_like(self._u)
        self._applied = np.zeros_like(self._u)

    def write(self, wrench: np.ndarray) -> None:
        self._u = np.array(wrench, dtype=float)

    def read(self, dt: float) -> DeviceReading:
        model, user = self._require()
        if not self._active:
            raise DeviceError(f'{self.name}: read() before activate()')
        status = model.step(self._u, self._f_h, dt)
        self._applied = model.applied
        self._t += dt
        self._f_h = user.wrench(self._t, model.pose, model.twist)
        return self._reading(model, dt, status)

    def idle(self, dt: float) -> DeviceReading:
        if self._applied.any():
            self._applied = np.zeros_like(self._applied)
        return self._reading(self._require()[0], dt)

    def carry_over(self) -> bytes:
        """The device's true state, its sensor's (the noise generator, the velocity filter)
        and the user's clock: a new instance resumed from it continues bit for bit as this
        one would after ``activate``."""
        model, _ = self._require()
        return pickle.dumps((model, self._sensor, self._t, self._f_h))

    def resume(self, carried: bytes) -> None:
        model, _ = self._require()
        carried_model, sensor, t, f_h = pickle.loads(carried)
        dim = carried_model.params.task.dim
        if dim != model.params.task.dim:
            raise DeviceError(f'{self.name}: resume(): a carried state of task dimension {dim},'
                              f' configured for {model.params.task.dim}')
        self._model, self._sensor, self._t, self._f_h = carried_model, sensor, t, f_h

    @property
    def applied(self) -> np.ndarray:
        """The wrench the simulated device applies (N, N m, after its own saturation): that of
        its newest step, zero while parked (``idle``) and once deactivated. What a test sees
        reach the device."""
        return self._applied.copy()


#: Built-in backends by name: the class, or ``'module:Class'`` of one imported only when it
#: is selected (so that importing this module imports neither rclpy nor sockets' users).
BUILTIN_BACKENDS: dict[str, type[DeviceBackend] | str] = {
    SimMaglevBackend.name: SimMaglevBackend,
    'ros_topics': 'haptic_topology.nodes.topic_backend:RosTopicBackend',
    'network': 'haptic_topology.remote.network:NetworkBackend',
    'forcedimension': 'haptic_topology.device.forcedimension:ForceDimensionBackend',
    'forcedimension_emulator':
        'haptic_topology.device.forcedimension:ForceDimensionEmulatorBackend',
    'openhaptics': 'haptic_topology.device.openhaptics:OpenHapticsBackend',
    'haply': 'haptic_topology.remote.haply:HaplyBackend',
}


def zero_and_release(backend: DeviceBackend, dim: int) -> list[str]:
    """Write a zero wrench (``dim`` components), then :meth:`DeviceBackend.deactivate`: the
    end of every active period, a failed activation's included. Whatever either raises
    (a backend's own code: any exception), both are tried; returns what went wrong, a line
    each, for the caller's log."""
    problems = []
    for what, call in (('writing zero wrench', lambda: backend.write(np.zeros(dim))),
                       ('deactivate()', backend.deactivate)):
        try:
            call()
        except Exception as exc:        # reported: the release goes on
            problems.append(f'{backend.name}: {what} failed: {type(exc).__name__}: {exc}')
    return problems


def activate_backend(backend: DeviceBackend, dim: int) -> None:
    """``backend.activate()``; when it raises, the device is zeroed and released
    (:func:`zero_and_release`, ``dim`` components) and a
    :class:`~haptic_topology.errors.DeviceError` is raised with the backend's reason
    (:func:`~haptic_topology.errors.error_line`) and whatever went wrong releasing it."""
    try:
        backend.activate()
    except Exception as exc:            # a backend's own code: its reason is the fault
        raise DeviceError('; '.join([error_line(exc, f'{backend.name}: activate()'),
                                     *zero_and_release(backend, dim)])) from exc


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
        if isinstance(cls, str):
            cls = _import_class(cls)
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


def create_backend(name: str, lockstep: bool = False) -> DeviceBackend:
    """An unconfigured instance of the backend called ``name``; ``lockstep``: for a driver
    on the simulated clock, which a device on its own clock cannot follow (refused)."""
    backend = backend_class(name)()
    if lockstep and not backend.lockstep:
        raise DeviceError(f'backend {name}: the device runs on its own clock, so clock: '
                          'lockstep cannot pace it (expected clock: wall, or a backend that '
                          'advances only when read: sim_maglev)')
    return backend
