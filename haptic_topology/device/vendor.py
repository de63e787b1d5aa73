"""What every vendor device backend shares (Force Dimension, OpenHaptics, Haply): the mapping of
a 3-axis device's handle to a point task, its grasp and clutch buttons, its identity, and the
registry that ``haptic-topology devices`` and ``run`` ask whether a vendor library is there.

No rclpy, no vendor package here: a backend imports its vendor's Python package itself, lazily
(in :meth:`~haptic_topology.device.backend.DeviceBackend.configure` or through its
:class:`VendorSupport`), so a missing SDK is one
:class:`~haptic_topology.errors.VendorLibraryMissing` line, never an import failure of this
package.

**API** (stable; the vendor backends build on it):

* :data:`VENDOR_OPTIONS` and :func:`parse_vendor_options`: the options every vendor backend
  takes (``axes``, ``origin``, ``scale``, ``force_scale``, ``engage_button``,
  ``clutch_button``, ``grasp_ramp_ms``), checked, plus the backend's own (returned apart);
* :class:`VendorHand`: per cycle, :meth:`VendorHand.reading` turns the device's position,
  velocity and button mask into the task's
  :class:`~haptic_topology.device.backend.DeviceReading`, and :meth:`VendorHand.force` the
  task wrench ``u`` into the device force; :attr:`VendorHand.pose` is the task pose it
  reports now;
* :class:`DeviceIdentity`: vendor, model, serial, SDK, workspace -> ``hardware_id`` and
  diagnostics values (which ``/diagnostics`` carries into the bag and ``summary.json``);
* :class:`VendorBackend`: the base of a 3-axis vendor backend (its axes, the options and
  the hand at ``configure``, ``hardware_id`` and diagnostics values from the identity);
  :func:`optional_number` and :func:`flag_option` check a backend's own options;
* :data:`VENDOR_BACKENDS`, :class:`VendorSupport`, :func:`vendor_support`,
  :func:`require_library`, :func:`probe`: the registry (backend name -> its support).

**Mapping.** The handle is a point (the task is ``planar_point``, x y, or ``spatial_point``,
x y z; a 3-axis device renders no torque,
:data:`~haptic_topology.device.backend.TRANSLATION_AXES`). Its device position ``p_D``
(device units, device frame ``D``) maps to the task position ``p_T = p_o + M s p_D + c``
through the same :class:`~haptic_topology.device.topic_mapping.TopicMapping` as the
``ros_topics`` backend (``M`` from ``axes``, ``p_o`` =
``origin``, ``s`` = ``scale``; a planar task keeps x and y), plus ``c``, the offset that
grasping and the clutch accumulate (below). A task force ``f_T`` (N) is the device force
``M^T f_T / k_f`` (``k_f`` = ``force_scale``); a planar task's force has no z.

**Grasp and clutch.** The hand *grasps* while the ``engage_button`` is held (no engage
button: always) and the ``clutch_button`` is not. While it does not grasp, the device gets
zero force, the task position stays where it was (twist zero) and the reading carries
``DeviceStatus.WATCHDOG`` (the output is not the command), so the device moves freely and the
linkage does not (indexing). When it grasps again, ``c`` takes up the distance the handle
moved meanwhile, so the task position goes on from where it stayed, and the force fades in
from zero over ``grasp_ramp_ms`` (WATCHDOG while it does). At the start the task position is
the scenario's hand (``initial_pose``): the first grasp is where the linkage is. With an
explicit ``origin`` the first grasp keeps the absolute mapping (``c`` = 0) instead.

**Letting go after a fault.** :meth:`VendorHand.release` (a backend calls it when its device
comes back after a loss, e.g. a reconnection) lets go as the clutch does, and the hand then
grasps again only after the buttons have asked to let go once: the engage button released
and pressed again, or the clutch button pressed and released; a button held all along does
not count. With neither button configured the hand stays released until the next
activation (a new hand). The grasp that follows is an ordinary one: the task position goes
on from where it stayed and the force fades in over ``grasp_ramp_ms``.

Example (checked by ``test/unit/device/test_vendor.py``): ``spatial_point`` starting at
(0.1, 0, 0), mm device (``scale: 0.001``), clutch on button 1. The handle at (10, 0, 0) mm
reads (0.1, 0, 0) (the first grasp aligns it); moved to (20, 0, 0) mm it reads (0.11, 0, 0);
clutched and moved back to (0, 0, 0) mm it still reads (0.11, 0, 0); released there and
moved to (5, 0, 0) mm it reads (0.115, 0, 0).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from haptic_topology.device.backend import (
    TRANSLATION_AXES,
    BackendConfig,
    DeviceAxes,
    DeviceBackend,
    DeviceReading,
)
from haptic_topology.device.topic_mapping import TopicMapping, option_error, parse_axes
from haptic_topology.errors import DeviceError, HapticTopologyError, VendorLibraryMissing
from haptic_topology.vocabulary import DeviceStatus, TaskSpace

#: The options every vendor backend takes, with their defaults (see the module doc and the
#: table in docs/devices.md). ``origin`` None: the first grasp is where the scenario's hand
#: starts; a button None: none.
VENDOR_OPTIONS: dict[str, Any] = {
    'axes': ['x', 'y', 'z'], 'origin': None, 'scale': 1.0, 'force_scale': 1.0,
    'engage_button': None, 'clutch_button': None, 'grasp_ramp_ms': 50.0,
}
#: Highest button index (a 32-bit button mask).
MAX_BUTTON = 31
_WATCHDOG = int(DeviceStatus.WATCHDOG)


@dataclass(frozen=True)
class VendorOptions:
    """The common options, checked: ``mapping`` (its task is ``spatial``: the point rows are
    taken from it), ``explicit_origin``, the buttons (bit index or None), ``ramp`` (s)."""

    task: TaskSpace
    mapping: TopicMapping
    explicit_origin: bool
    engage_button: int | None
    clutch_button: int | None
    ramp: float


def _number(options: Mapping[str, Any], key: str, backend: str, lo: float, hi: float,
            open_lo: bool = True) -> float:
    value = options.get(key, VENDOR_OPTIONS[key])
    ok = (not isinstance(value, bool) and isinstance(value, int | float)
          and math.isfinite(value) and (value > lo if open_lo else value >= lo) and value <= hi)
    if not ok:
        bracket = '(' if open_lo else '['
        raise option_error(key, f'a number in {bracket}{lo:g}, {hi:g}]', value, backend)
    return float(value)


def _button(options: Mapping[str, Any], key: str, backend: str) -> int | None:
    value = options.get(key, VENDOR_OPTIONS[key])
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_BUTTON:
        raise option_error(key, f'a button index 0-{MAX_BUTTON} or null (none)', value, backend)
    return value


def parse_vendor_options(options: Mapping[str, Any], backend: str, task: TaskSpace,
                         own: Mapping[str, Any]) -> tuple[VendorOptions, dict[str, Any]]:
    """Check ``options`` (a backend's ``backend_options``) for the point task ``task``:
    the common options (:data:`VENDOR_OPTIONS`) and the backend's own, ``own`` (name ->
    default). Returns the common ones parsed and the backend's own with their defaults filled
    in (its to check). An unknown key, a bad value or a task that is not a point grasp raises
    :class:`~haptic_topology.errors.DeviceError` naming ``backend``, the field and what it must
    be."""
    if not isinstance(options, Mapping):
        raise DeviceError(f'{backend}: backend_options: expected a mapping, got {options!r}')
    if not task.point:
        raise DeviceError(f'{backend}: a {task.value} task needs torque; a 3-axis device '
                          'renders a point grasp only (planar_point, spatial_point)')
    known = {**VENDOR_OPTIONS, **own}
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise DeviceError(f'{backend}: backend_options: unknown option {unknown[0]!r} '
                          f'(expected some of: {", ".join(sorted(known))})')
    origin = options.get('origin')
    if origin is None:
        p_o = np.zeros(3)
    elif (isinstance(origin, list) and len(origin) == 3
          and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                  for v in origin)):
        p_o = np.array(origin, dtype=float)
    else:
        raise option_error('origin', '3 numbers: the task position x, y, z (m) of the device '
                           'origin, or null (the first grasp is where the hand starts)',
                           origin, backend)
    rotation = parse_axes(options.get('axes', VENDOR_OPTIONS['axes']), backend)
    mapping = TopicMapping(TaskSpace.SPATIAL, rotation, p_o,
                           _number(options, 'scale', backend, 0.0, math.inf),
                           _number(options, 'force_scale', backend, 0.0, math.inf))
    engage = _button(options, 'engage_button', backend)
    clutch = _button(options, 'clutch_button', backend)
    if engage is not None and engage == clutch:
        raise option_error('clutch_button', f'another button than engage_button ({engage})',
                           clutch, backend)
    ramp = 1e-3 * _number(options, 'grasp_ramp_ms', backend, 0.0, 10_000.0, open_lo=False)
    rest = {k: options.get(k, v) for k, v in own.items()}
    return VendorOptions(task, mapping, origin is not None, engage, clutch, ramp), rest


class VendorHand:
    """The handle of a 3-axis device as the task sees it (module doc: mapping, grasp,
    clutch): a pure object, fed the device's samples, deterministic. ``start``: the task pose
    the run starts from (the scenario's hand, ``BackendConfig.initial_pose``)."""

    def __init__(self, opts: VendorOptions, start: np.ndarray) -> None:
        self.opts = opts
        m = opts.task.dim
        start = np.asarray(start, dtype=float)
        if start.shape != (m,):
            raise DeviceError(f'initial pose: expected {m} numbers for a {opts.task.value} '
                              f'task, got {start.shape}')
        self._m = m
        self._held = [float(v) for v in start] + [0.0] * (3 - m)   # task x, y, z held
        self._offset: list[float] | None = None if not opts.explicit_origin else [0.0] * 3
        self._first = True
        self.grasping = False
        self.scale = 0.0                 # the fade of the force, 0..1
        self.grasps = 0                  # times the hand took hold
        self.clutched_cycles = 0         # cycles read while not grasping
        #: The task wrench (N, ``m`` entries) of the newest :meth:`force`: what the device
        #: was sent, in task terms (zero while not grasping, faded, limited).
        self.sent = np.zeros(m)
        #: Whether the newest :meth:`force` was limited in magnitude.
        self.clamped = False
        self.released = False            # let go by release(); waiting for a let-go request

    def _wants(self, buttons: int) -> bool:
        o = self.opts
        engaged = o.engage_button is None or bool(buttons >> o.engage_button & 1)
        clutched = o.clutch_button is not None and bool(buttons >> o.clutch_button & 1)
        return engaged and not clutched

    def reading(self, p: tuple[float, float, float], v: tuple[float, float, float],
                buttons: int, dt: float) -> DeviceReading:
        """The task reading of the device at position ``p`` and velocity ``v`` (device units
        and frame) with ``buttons`` (bit i: button i held), ``dt`` s after the previous one.
        The hand wrench is zero (a 3-axis device does not measure it). The caller checks
        that ``p`` and ``v`` are finite (a device that reports NaN is at fault)."""
        mp = self.opts.mapping.point(p)
        wants = self._wants(buttons)
        if self.released:
            if wants:
                wants = False            # still the grasp of before the release
            else:
                self.released = False    # the buttons let go: the next request grasps
        if wants and not self.grasping:
            if self._offset is None or not self._first:
                self._offset = [h - q for h, q in zip(self._held, mp, strict=True)]
            self.grasps += 1
            self._first = False
        self.grasping = wants
        m = self._m
        if wants:
            off = self._offset
            assert off is not None
            self._held = [mp[0] + off[0], mp[1] + off[1], mp[2] + off[2]]
            ramp = self.opts.ramp
            self.scale = 1.0 if ramp <= 0.0 else min(1.0, self.scale + dt / ramp)
            tv = self.opts.mapping.point_velocity(v)
            twist = np.array(tv[:m])
        else:
            self.scale = 0.0
            self.clutched_cycles += 1
            twist = np.zeros(m)
        status = DeviceStatus.OK if self.scale >= 1.0 else DeviceStatus.WATCHDOG
        return DeviceReading(np.array(self._held[:m]), twist, np.zeros(m), status)

    def release(self) -> None:
        """Let go (zero force from now on) until the buttons have asked to let go once and
        then to grasp (module doc, "Letting go after a fault")."""
        self.released = True
        self.grasping = False
        self.scale = 0.0

    def regrasp_hint(self) -> str:
        """What the user does to grasp again after :meth:`release`, for an operator's
        message."""
        o = self.opts
        if o.engage_button is not None:
            return f'release and press the engage button (button {o.engage_button}) to grasp again'
        if o.clutch_button is not None:
            return (f'press and release the clutch button (button {o.clutch_button}) to grasp '
                    'again')
        return ('no engage or clutch button is configured: forces resume at the next '
                'activation of device_driver')

    @property
    def pose(self) -> np.ndarray:
        """The task pose it reports now (where the hand holds the linkage, or held it)."""
        return np.array(self._held[:self._m])

    def force(self, u: np.ndarray, limit: float = math.inf) -> tuple[float, float, float]:
        """The device force (device units and frame) of the task wrench ``u`` (N; already
        clamped and finite, ``m`` entries): zero while not grasping, faded in after a grasp
        (module doc), its magnitude limited to ``limit`` (device units; the direction kept:
        the device's own force limit). Non-finite entries are taken as zero. What it amounts
        to in task terms is kept in :attr:`sent` (the trace's ``applied``)."""
        self.clamped = False
        if not self.grasping or self.scale <= 0.0:
            self.sent = np.zeros(self._m)
            return 0.0, 0.0, 0.0
        k = self.scale
        f = [k * float(x) if math.isfinite(x) else 0.0 for x in u]
        fz = f[2] if self._m == 3 else 0.0
        out = self.opts.mapping.point_force((f[0], f[1], fz))
        if limit < math.inf:
            norm = math.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2])
            if norm > limit:            # the device's limit, the direction kept
                c = limit / norm
                self.clamped = True
                out = (c * out[0], c * out[1], c * out[2])
                f = [c * x for x in f]
        self.sent = np.array(f[:self._m])
        return out

    def values(self) -> dict[str, str]:
        """Diagnostics values: grasping, grasps, clutched cycles."""
        return {'grasping': 'true' if self.grasping else 'false', 'grasps': str(self.grasps),
                'not_grasping_cycles': str(self.clutched_cycles)}


@dataclass(frozen=True)
class DeviceIdentity:
    """What identifies a vendor's unit: ``vendor`` (e.g. ``Force Dimension``), ``model``
    (``omega.3``), ``serial`` (text; empty when the device has none), ``sdk`` (the vendor
    library's version), ``workspace`` (text, e.g. ``sphere r 0.075 m``; empty: unknown)."""

    vendor: str
    model: str
    serial: str = ''
    sdk: str = ''
    workspace: str = ''

    def hardware_id(self, backend: str) -> str:
        """``'<backend> <model> serial <serial>'`` (the driver's ``hardware_id``, printed by
        ``run`` as ``device: backend ...`` and kept in the bag's ``/diagnostics``)."""
        serial = f' serial {self.serial}' if self.serial else ''
        return f'{backend} {self.model}{serial}'

    def values(self) -> dict[str, str]:
        """``device_vendor``, ``device_model``, ``device_serial``, ``device_sdk``,
        ``device_workspace``: diagnostics values (``run`` copies them into ``summary.json``)."""
        return {'device_vendor': self.vendor, 'device_model': self.model,
                'device_serial': self.serial, 'device_sdk': self.sdk,
                'device_workspace': self.workspace}


#: The diagnostics keys of a :class:`DeviceIdentity`.
IDENTITY_KEYS = ('device_vendor', 'device_model', 'device_serial', 'device_sdk',
                 'device_workspace')


def optional_number(value: Any, key: str, backend: str, hi: float, meaning: str) -> float | None:
    """A backend's own option that is a number in (0, ``hi``] or null (None; ``meaning``:
    what null means, for the message); else a :class:`~haptic_topology.errors.DeviceError`
    naming the field."""
    if value is None:
        return None
    if (isinstance(value, bool) or not isinstance(value, int | float)
            or not (math.isfinite(value) and 0.0 < value <= hi)):
        raise option_error(key, f'a number in (0, {hi:g}] or null ({meaning})', value, backend)
    return float(value)


def flag_option(value: Any, key: str, backend: str) -> bool:
    """A backend's own option that is true or false."""
    if not isinstance(value, bool):
        raise option_error(key, 'true or false', value, backend)
    return value


class VendorBackend(DeviceBackend):
    """The base of a 3-axis vendor device backend: it senses and actuates x, y, z forces
    (:data:`~haptic_topology.device.backend.TRANSLATION_AXES`; point tasks only), runs on its
    own clock, and at :meth:`configure` checks the common options (:data:`VENDOR_OPTIONS`)
    and its own (:attr:`own_options`, checked by :meth:`configure_own`), then makes its
    :class:`VendorHand` and keeps the task. Once a device is opened, ``identity`` (set by
    the backend) gives ``hardware_id`` (``'<name> <model> serial <serial>'``) and the
    diagnostics values, with the hand's."""

    lockstep = False
    #: The backend's own options (name -> default), besides
    #: :data:`~haptic_topology.device.vendor.VENDOR_OPTIONS`.
    own_options: ClassVar[dict[str, Any]] = {}

    def __init__(self) -> None:
        self._hand: VendorHand | None = None
        self._start = np.zeros(0)
        self._m = 0
        self.identity: DeviceIdentity | None = None

    @classmethod
    def axes(cls, options: Mapping[str, Any]) -> DeviceAxes:
        """x, y, z sensed and actuated (the device's rotations, where it has them, unused)."""
        del options
        return TRANSLATION_AXES

    def configure(self, config: BackendConfig) -> None:
        opts, own = parse_vendor_options(config.options, self.name, config.params.task,
                                         self.own_options)
        self.configure_own(own)
        self._hand = VendorHand(opts, config.initial_pose)
        self._start = np.array(config.initial_pose, dtype=float)
        self._m = self.keep_task(config).dim

    def configure_own(self, own: dict[str, Any]) -> None:
        """Check and keep the backend's own options (``own``: :attr:`own_options` with what
        ``backend_options`` set); raise :class:`~haptic_topology.errors.DeviceError` naming a
        bad one. Default: nothing to check."""
        del own

    def hand(self) -> VendorHand:
        """The hand (after ``configure``; else a :class:`~haptic_topology.errors.DeviceError`
        saying so)."""
        if self._hand is None:
            raise DeviceError(f'{self.name}: used before configure()')
        return self._hand

    @property
    def hardware_id(self) -> str:
        """``'<name> <model> serial <serial>'`` once a device was opened; before,
        ``'<name> <task>'`` (configured) or ``'<name>'``."""
        if self.identity is None:
            return super().hardware_id
        return self.identity.hardware_id(self.name)

    def written(self, wrench: np.ndarray) -> np.ndarray:
        """The task wrench the device was sent by the newest ``write(wrench)``
        (:attr:`VendorHand.sent`: zero while the hand does not grasp, faded after a grasp,
        limited by the device's force limit)."""
        return wrench if self._hand is None else self._hand.sent

    def values(self) -> dict[str, str]:
        """The identity's values and the hand's
        (:meth:`~haptic_topology.device.vendor.VendorHand.values`); a backend adds
        its own counters."""
        out = {} if self.identity is None else self.identity.values()
        if self._hand is not None:
            out.update(self._hand.values())
        return out


# -- the registry ---------------------------------------------------------------------------
@dataclass(frozen=True)
class VendorSupport:
    """What ``haptic-topology devices`` and ``run`` need of a vendor backend ``backend``: its
    Python ``package`` (distribution name), the vendor ``library``, the environment
    ``variable`` that points to it, ``load`` (imports the binding; returns what it loaded,
    e.g. the library's path and version; raises
    :class:`~haptic_topology.errors.VendorLibraryMissing` when the package or the library is
    missing) and ``devices`` (after a successful ``load``: one text per connected device,
    e.g. its model and serial; may raise :class:`~haptic_topology.errors.HapticTopologyError`)."""

    backend: str
    package: str
    library: str
    variable: str
    load: Callable[[], str]
    devices: Callable[[], list[str]]

    def missing(self, detail: str) -> VendorLibraryMissing:
        """The one-line error of this backend's missing package or library."""
        return VendorLibraryMissing(self.backend, self.package, self.library, self.variable,
                                    detail)


#: Vendor backends: name -> ``'module:function'`` returning its :class:`VendorSupport`,
#: imported only when asked (the backends register themselves here).
VENDOR_BACKENDS: dict[str, str] = {
    'forcedimension': 'haptic_topology.device.forcedimension:support',
    'forcedimension_emulator': 'haptic_topology.device.forcedimension:support',
    'openhaptics': 'haptic_topology.device.openhaptics:support',
    'haply': 'haptic_topology.remote.haply:vendor_support',
}


def vendor_support(name: str) -> VendorSupport | None:
    """The :class:`VendorSupport` of the backend ``name``, None if it is not a vendor
    backend."""
    spec = VENDOR_BACKENDS.get(name)
    if spec is None:
        return None
    module, _, attr = spec.partition(':')
    support: VendorSupport = getattr(importlib.import_module(module), attr)()
    return support


def require_library(name: str) -> None:
    """Before a run: raise :class:`~haptic_topology.errors.VendorLibraryMissing` (one line,
    exit status 2) when ``name`` is a vendor backend whose package or library is missing."""
    support = vendor_support(name)
    if support is not None:
        support.load()


@dataclass(frozen=True)
class VendorProbe:
    """What ``haptic-topology devices`` prints of one vendor backend: whether its library
    loads (``found``), what was said (``detail``: where, or why not), its devices."""

    support: VendorSupport
    found: bool
    detail: str
    devices: tuple[str, ...] = ()


def probe(name: str) -> VendorProbe:
    """Load the vendor backend ``name``'s library and list its devices (a failure of either,
    a missing library or one that does not load, is reported in the probe, never raised)."""
    support = vendor_support(name)
    if support is None:
        raise DeviceError(f'{name}: not a vendor backend (expected one of '
                          f'{", ".join(sorted(VENDOR_BACKENDS))})')
    try:
        where = support.load()
    except VendorLibraryMissing as exc:
        return VendorProbe(support, False, exc.detail or str(exc))
    except HapticTopologyError as exc:  # e.g. another copy of the library loaded already
        return VendorProbe(support, False, str(exc))
    try:
        devices = tuple(support.devices())
    except HapticTopologyError as exc:
        return VendorProbe(support, True, f'{where}; listing devices failed: {exc}')
    return VendorProbe(support, True, where, devices)
