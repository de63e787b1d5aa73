"""Simulated haptic device: ``M_d xdd + C_d xd = F_h + u`` (eq. 9) with hard stops, saturation
and, as options, the imperfections of a real device.

Task vectors at the user's hand as in :mod:`haptic_topology.dynamics.taskspace` (planar: x, y,
theta; spatial: x, y, z and the orientation as a rotation vector, world frame; twists with the
angular velocity in the world frame). ``M_d`` is the device inertia (kg, kg m^2; any symmetric
positive definite m x m matrix, e.g. a 6 x 6 spatial inertia with translation-rotation
coupling), ``C_d`` the Christoffel (velocity) matrix, here constant (N s/m, N m s/rad). The
planar maglev of the paper's lab is modelled with ``M_d = I`` (Section VI).

Limits: translational hard stops per axis (m), planar theta stops (rad), and for a spatial
device an orientation cone: the rotation from a centre orientation is at most ``max_angle``
(rad). The control wrench ``u`` saturates per axis (N, N m).

Realism (:class:`DeviceRealism`, all off by default, so that the paper's ideal device is the
default): position sensor quantization and Gaussian noise (seeded), velocity estimated from the
measured positions through a first-order low-pass filter, one cycle of actuation delay, viscous
and Coulomb friction. None of them is known to the controller: friction is not part of the
``C_d`` that eq. 10 compensates.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from haptic_topology.dynamics.taskspace import pose_difference
from haptic_topology.errors import ConfigError
from haptic_topology.validate import (
    as_angles,
    as_float,
    as_int,
    as_str,
    as_vector,
    check_keys,
)
from haptic_topology.vocabulary import DeviceStatus, TaskSpace


class VelocitySource(enum.Enum):
    """Where the device's reported twist comes from."""

    MODEL = 'model'             # the model's exact twist (an ideal velocity sensor)
    DIFFERENCE = 'difference'   # backward difference of measured poses, low-pass filtered


@dataclass(frozen=True)
class DeviceRealism:
    """Imperfections of the simulated device; the defaults switch every one off.

    Sensor (what the device reports, not how it moves): ``quantization`` (m values, m / rad per
    count; 0 = none), ``noise_std`` (m values, m / rad, Gaussian, added before quantization,
    drawn from ``numpy.random.default_rng(seed)``: the same seed gives the same run),
    ``velocity`` (:class:`VelocitySource`) with ``velocity_cutoff_hz`` (Hz) of the first-order
    low-pass applied to the differenced velocity (0 = unfiltered).
    Actuator: ``actuation_delay`` (cycles, 0 or 1): the wrench written in cycle k acts in cycle
    k + 1. Friction (in eq. 9, unknown to the controller): ``viscous`` (m values, N s/m,
    N m s/rad) and ``coulomb`` (m values, N, N m; stick-slip, exact for a diagonal ``M_d``).
    """

    quantization: np.ndarray = field(default_factory=lambda: np.zeros(0))
    noise_std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seed: int = 0
    velocity: VelocitySource = VelocitySource.MODEL
    velocity_cutoff_hz: float = 0.0
    actuation_delay: int = 0
    viscous: np.ndarray = field(default_factory=lambda: np.zeros(0))
    coulomb: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def is_ideal(self) -> bool:
        """True when no option is on (the device of the paper)."""
        return (not np.any(self.quantization) and not np.any(self.noise_std)
                and self.velocity is VelocitySource.MODEL and self.actuation_delay == 0
                and not np.any(self.viscous) and not np.any(self.coulomb))

    def labels(self) -> list[str]:
        """Short names of the options that are on (for tables)."""
        out = []
        if np.any(self.quantization):
            out.append('quantization')
        if np.any(self.noise_std):
            out.append('noise')
        if self.velocity is VelocitySource.DIFFERENCE:
            out.append('velocity from positions')
        if self.actuation_delay:
            out.append('actuation delay')
        if np.any(self.viscous):
            out.append('viscous friction')
        if np.any(self.coulomb):
            out.append('Coulomb friction')
        return out


@dataclass(frozen=True)
class DeviceParams:
    """Device model parameters (task vectors of length m = task.dim).

    ``mass`` (m x m, symmetric positive definite; kg, kg m^2) and ``christoffel`` (m x m,
    N s/m, N m s/rad): ``M_d`` and ``C_d`` of eq. 9. ``workspace_lo``/``workspace_hi``: hard
    stops per pose coordinate (m / rad; +-inf for none; a spatial device's rotation-vector
    entries are always +-inf, its orientation is limited by ``max_angle``).
    ``wrench_limit``: symmetric saturation of u per coordinate (N / N m). ``max_angle`` (rad,
    spatial only): largest rotation away from ``orientation_center`` (rotation vector, world
    frame; None = the device's initial orientation). ``realism``: see :class:`DeviceRealism`.
    """

    task: TaskSpace
    mass: np.ndarray
    christoffel: np.ndarray
    workspace_lo: np.ndarray
    workspace_hi: np.ndarray
    wrench_limit: np.ndarray
    max_angle: float = math.inf
    orientation_center: np.ndarray | None = None
    realism: DeviceRealism = field(default_factory=DeviceRealism)

    @classmethod
    def unlimited(cls, task: TaskSpace, mass: float = 1.0) -> DeviceParams:
        m = task.dim
        inf = np.full(m, np.inf)
        return cls(task, np.eye(m) * mass, np.zeros((m, m)), -inf, inf, inf.copy())


def _matrix_or_diagonal(value: Any, where: str, m: int, positive_definite: bool) -> np.ndarray:
    """``m`` numbers (the diagonal) or an m x m symmetric matrix (list of m rows)."""
    if isinstance(value, list) and value and all(isinstance(r, list) for r in value):
        if len(value) != m:
            raise ConfigError(f'{where}: expected {m} rows of {m} numbers, got {len(value)} rows')
        a = np.array([as_vector(r, f'{where}[{i}]', m) for i, r in enumerate(value)])
        if not np.allclose(a, a.T, rtol=0.0, atol=1e-12 * max(1.0, float(np.abs(a).max()))):
            raise ConfigError(f'{where}: expected a symmetric matrix, got {a.tolist()}')
        eig = np.linalg.eigvalsh(a)
        if positive_definite and eig.min() <= 0.0:
            raise ConfigError(f'{where}: expected a positive definite matrix, got eigenvalues '
                              f'{eig.tolist()}')
        if not positive_definite and eig.min() < 0.0:
            raise ConfigError(f'{where}: expected a positive semi-definite matrix, got '
                              f'eigenvalues {eig.tolist()}')
        return a
    return np.diag(as_vector(value, where, m, lo=0.0, lo_open=positive_definite))


def _realism_from_config(dev: Any, where: str, m: int) -> DeviceRealism:
    zeros = [0.0] * m
    sensor = check_keys(dev.get('sensor', {}), f'{where}.sensor', optional=(
        'quantization', 'noise_std', 'seed', 'velocity', 'velocity_cutoff_hz'))
    ws = f'{where}.sensor'
    quant = as_vector(sensor.get('quantization', zeros), f'{ws}.quantization', m, lo=0.0)
    noise = as_vector(sensor.get('noise_std', zeros), f'{ws}.noise_std', m, lo=0.0)
    seed = as_int(sensor.get('seed', 0), f'{ws}.seed', lo=0)
    velocity = VelocitySource(as_str(sensor.get('velocity', 'model'), f'{ws}.velocity',
                                     [v.value for v in VelocitySource]))
    if 'velocity_cutoff_hz' in sensor and velocity is VelocitySource.MODEL:
        raise ConfigError(f'{ws}.velocity_cutoff_hz: only used with velocity: difference '
                          '(the model velocity is not filtered)')
    cutoff = as_float(sensor.get('velocity_cutoff_hz', DEFAULT_VELOCITY_CUTOFF_HZ),
                      f'{ws}.velocity_cutoff_hz', lo=0.0)
    delay = as_int(dev.get('actuation_delay', 0), f'{where}.actuation_delay', lo=0, hi=1)
    fr = check_keys(dev.get('friction', {}), f'{where}.friction',
                    optional=('viscous', 'coulomb'))
    viscous = as_vector(fr.get('viscous', zeros), f'{where}.friction.viscous', m, lo=0.0)
    coulomb = as_vector(fr.get('coulomb', zeros), f'{where}.friction.coulomb', m, lo=0.0)
    return DeviceRealism(quant, noise, seed, velocity, cutoff, delay, viscous, coulomb)


#: Low-pass cutoff (Hz) of the differenced velocity when ``velocity_cutoff_hz`` is not given.
DEFAULT_VELOCITY_CUTOFF_HZ = 100.0


def device_from_config(raw: Any, where: str, task: TaskSpace) -> tuple[DeviceParams, np.ndarray]:
    """The ``device:`` block of a scenario: its :class:`DeviceParams` and the initial offset
    (device pose - VT hand pose, m / rad). ``where``: the block's path (``file: scenario.device``).

    Keys (all optional; defaults give the ideal device of the paper):

    * ``offset``: m values (m / rad), default 0;
    * ``mass``: M_d of eq. 9, m values (the diagonal, > 0) or an m x m symmetric positive
      definite matrix (kg, kg m^2), default I; ``christoffel``: C_d, m values >= 0 or a
      symmetric positive semi-definite matrix (N s/m, N m s/rad), default 0;
    * ``workspace``: absolute hard stops ``{lo, hi}`` (``pi`` expressions accepted; default
      none): planar 3 values (m, m, rad); spatial 3 translation values (m) plus, optionally,
      ``max_angle`` (rad, in (0, pi]) and ``center`` (rotation vector, rad, world frame;
      default the device's initial orientation) for the orientation;
    * ``wrench_limit``: > 0 per axis (N / N m), default 1e9;
    * ``sensor: {quantization, noise_std, seed, velocity: model|difference,
      velocity_cutoff_hz}``, ``actuation_delay`` (0 or 1 cycles), ``friction: {viscous,
      coulomb}``: :class:`DeviceRealism` (all off by default; cutoff default
      :data:`DEFAULT_VELOCITY_CUTOFF_HZ`).
    """
    m = task.dim
    dev = check_keys(raw, where, optional=(
        'offset', 'mass', 'christoffel', 'workspace', 'wrench_limit', 'sensor',
        'actuation_delay', 'friction'))
    offset = as_vector(dev.get('offset', [0.0] * m), f'{where}.offset', m)
    mass = _matrix_or_diagonal(dev.get('mass', [1.0] * m), f'{where}.mass', m, True)
    chris = _matrix_or_diagonal(dev.get('christoffel', [0.0] * m), f'{where}.christoffel', m,
                                False)
    lo = np.full(m, -np.inf)
    hi = np.full(m, np.inf)
    max_angle = math.inf
    center: np.ndarray | None = None
    if 'workspace' in dev:
        wk = f'{where}.workspace'
        if task is TaskSpace.SPATIAL:
            ws = check_keys(dev['workspace'], wk, optional=('lo', 'hi', 'max_angle', 'center'))
            if ('lo' in ws) != ('hi' in ws):
                raise ConfigError(f'{wk}: give both lo and hi (3 translation stops each, m)')
            if 'lo' in ws:
                lo[:3] = _spatial_stops(ws['lo'], f'{wk}.lo')
                hi[:3] = _spatial_stops(ws['hi'], f'{wk}.hi')
            if 'max_angle' in ws:
                max_angle = as_float(_angle(ws['max_angle'], f'{wk}.max_angle'),
                                     f'{wk}.max_angle', lo=0.0, lo_open=True, hi=math.pi)
            if 'center' in ws:
                if 'max_angle' not in ws:
                    raise ConfigError(f'{wk}.center: only used with max_angle')
                center = as_angles(ws['center'], f'{wk}.center', 3)
        else:
            ws = check_keys(dev['workspace'], wk, required=('lo', 'hi'))
            lo = as_angles(ws['lo'], f'{wk}.lo', m)
            hi = as_angles(ws['hi'], f'{wk}.hi', m)
        if np.any(lo >= hi):
            raise ConfigError(f'{wk}: expected lo < hi on every axis, got lo='
                              f'{lo.tolist()} hi={hi.tolist()}')
    limit = as_vector(dev.get('wrench_limit', [1e9] * m), f'{where}.wrench_limit', m,
                      lo=0.0, lo_open=True)
    realism = _realism_from_config(dev, where, m)
    return DeviceParams(task, mass, chris, lo, hi, limit, max_angle, center, realism), offset


def _spatial_stops(value: Any, where: str) -> np.ndarray:
    if isinstance(value, list) and len(value) == 6:
        raise ConfigError(f'{where}: a spatial device takes 3 translation stops (m); its '
                          'orientation is limited by workspace.max_angle (rad), not by '
                          'rotation-vector components')
    return as_angles(value, where, 3)


def _angle(value: Any, where: str) -> float:
    return float(as_angles([value], where, 1)[0])


#: ``device.compiled.clamp``, bound by the first :func:`saturate` call.
_clamp: Any = None


def saturate(wrench: np.ndarray, limit: np.ndarray) -> tuple[np.ndarray, bool]:
    """Clamp each coordinate of ``wrench`` to ``[-limit, limit]``; report whether any was.

    Non-finite entries are replaced by 0 (and reported as saturated), so that nothing but a
    finite wrench within the limits ever leaves this function.
    """
    # Compiled (device.compiled.clamp, which the simulated maglev's step also uses): it runs
    # twice per device cycle. Imported at the first call (see MaglevModel.__init__) and kept:
    # an import statement per call costs about as much as the clamp.
    global _clamp
    if _clamp is None:
        from haptic_topology.device.compiled import clamp as _clamp
    w = np.asarray(wrench, dtype=float)
    lim = np.asarray(limit, dtype=float)
    if w.shape != lim.shape or w.ndim != 1:
        raise ValueError(f'wrench must have {lim.size} entries (the limit\'s), got '
                         f'{w.size}')
    out = np.empty(lim.size)
    return out, bool(_clamp(w, lim, out))


#: ``maglev_step``'s bits (1 saturated, 2 stopped) as device status.
_STEP_STATUS = (DeviceStatus.OK, DeviceStatus.SATURATED, DeviceStatus.WORKSPACE_LIMIT,
                DeviceStatus.SATURATED | DeviceStatus.WORKSPACE_LIMIT)


class MaglevModel:
    """State and one-step integration of the simulated device (semi-implicit Euler).

    Each :meth:`step` integrates eq. 9, ``M_d xdd = F_h + u - C_d xd - F_friction``, with the
    saturated ``u`` (of the previous step when ``actuation_delay`` is 1), then enforces the
    hard stops. ``pose``/``twist`` are the true state; :class:`PositionSensor` reports it.
    """

    def __init__(self, params: DeviceParams, pose: np.ndarray,
                 twist: np.ndarray | None = None) -> None:
        m = params.task.dim
        if np.shape(pose) != (m,):
            raise ValueError(f'device pose must have {m} entries, got {np.shape(pose)}')
        self.params = params
        self.pose = np.array(pose, dtype=float)
        self.twist = np.zeros(m) if twist is None else np.array(twist, dtype=float)
        # Imported here: loading the compiled code costs about 1 s, which a process that
        # never steps a device does not pay.
        from haptic_topology.device.compiled import maglev_step
        self._step = maglev_step
        self._mass_inv = np.linalg.inv(params.mass)  # constant, inverted once
        self._mass_diag = np.diag(params.mass).copy()
        self.applied = np.zeros(m)
        self._pending = np.zeros(m)   # the wrench written last cycle (actuation delay)
        r = params.realism
        self._viscous = r.viscous if r.viscous.size else np.zeros(m)
        self._coulomb = r.coulomb if r.coulomb.size else np.zeros(m)
        # Terms that are exactly zero are skipped in step (x - 0.0 is x): the paper's device
        # has no C_d, no friction and no stops on some axes. Decided once, not per cycle.
        self._has_christoffel = bool(np.any(params.christoffel))
        self._has_viscous = bool(np.any(self._viscous))
        self._has_coulomb = bool(np.any(self._coulomb))
        self._has_stops = bool(np.any(np.isfinite(params.workspace_lo))
                               or np.any(np.isfinite(params.workspace_hi)))
        self._delay = bool(r.actuation_delay)
        self._rot_center = None
        if params.task is TaskSpace.SPATIAL and math.isfinite(params.max_angle):
            c = self.pose[3:6] if params.orientation_center is None else params.orientation_center
            self._rot_center_vec = np.array(c, dtype=float)
            self._rot_center = pin.exp3(self._rot_center_vec)
            # Squared distance |r - c|^2 of the rotation vectors within which the orientation
            # is inside the cone for certain (see _orientation_stop); the margin is many
            # orders above the rounding of the angle's own computation.
            self._inside_sq = (params.max_angle * (1.0 - 1e-9)) ** 2

    def __getstate__(self) -> dict[str, object]:
        # A compiled function pickles by value and compiles again where it is unpickled
        # (seconds): take it from the import instead.
        state = self.__dict__.copy()
        del state['_step']
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        from haptic_topology.device.compiled import maglev_step
        self.__dict__.update(state)
        self._step = maglev_step

    def step(self, u: np.ndarray, f_h: np.ndarray, dt: float) -> DeviceStatus:
        """Advance by ``dt`` (s) under control wrench ``u`` and hand wrench ``f_h`` (eq. 9;
        the arithmetic is :func:`~haptic_topology.device.compiled.maglev_step`)."""
        p = self.params
        m = self.pose.size
        pose, twist, applied = self.pose.copy(), self.twist.copy(), np.empty(m)
        bits = self._step(np.asarray(u, dtype=float), np.asarray(f_h, dtype=float), dt,
                          p.wrench_limit, self._mass_inv, self._mass_diag, p.christoffel,
                          self._viscous, self._coulomb, p.workspace_lo, p.workspace_hi,
                          self._delay, self._has_christoffel, self._has_viscous,
                          self._has_coulomb, self._has_stops, self._pending, pose, twist,
                          applied)
        self.pose, self.twist, self.applied = pose, twist, applied
        status = _STEP_STATUS[bits]
        if self._rot_center is not None and self._orientation_stop():
            status |= DeviceStatus.WORKSPACE_LIMIT
        return status

    def outside_workspace(self) -> str | None:
        """Where the pose lies beyond the hard stops (``workspace.lo``/``hi`` per coordinate,
        m / rad, and ``max_angle`` from the centre), in one line; None inside them."""
        p = self.params
        for i, (x, lo, hi) in enumerate(zip(self.pose, p.workspace_lo, p.workspace_hi,
                                                    strict=True)):
            if not lo <= x <= hi:
                return (f'at pose[{i}] = {x:.6g}, outside device.workspace '
                        f'[lo, hi] = [{lo:.6g}, {hi:.6g}]')
        if self._rot_center is not None:
            angle = float(np.linalg.norm(pin.log3(pin.exp3(self.pose[3:6])
                                                  @ self._rot_center.T)))
            if angle > p.max_angle:
                return (f'{angle:.6g} rad from device.workspace.center, beyond '
                        f'max_angle = {p.max_angle:.6g} rad')
        return None

    def _orientation_stop(self) -> bool:
        """Hold the orientation within ``max_angle`` of the centre; cancel the angular velocity
        that turns further away. Returns whether the stop was hit.

        The rotation angle from the centre is at most the distance ``|r - c|`` of the rotation
        vectors (SO(3) is positively curved, so its exponential map shortens distances): a
        pose that close to the centre is inside without the exponential and logarithm (the
        step then takes about 3.8 instead of 7.4 us)."""
        assert self._rot_center is not None
        d = self.pose[3:6] - self._rot_center_vec
        if d.dot(d) <= self._inside_sq:
            return False
        rot = pin.exp3(self.pose[3:6])
        away = pin.log3(rot @ self._rot_center.T)   # world-frame rotation from the centre
        angle = float(np.linalg.norm(away))
        limit = self.params.max_angle
        if angle <= limit:
            return False
        axis = away / angle
        self.pose[3:6] = pin.log3(pin.exp3(axis * limit) @ self._rot_center)
        w_out = float(axis @ self.twist[3:6])
        if w_out > 0.0:
            self.twist[3:6] -= w_out * axis
        return True


class PositionSensor:
    """What the device reports of its true state (see :class:`DeviceRealism`).

    ``measure(pose, twist, dt)`` returns the reported pose (true pose + noise, quantized per
    coordinate) and twist (the true twist, or the low-pass filtered backward difference of the
    reported poses: ``v_k = v_{k-1} + a ((x_k (-) x_{k-1}) / dt - v_{k-1})`` with
    ``a = 1 - exp(-2 pi f_c dt)``). Deterministic: the noise comes from a generator seeded
    with ``realism.seed``.
    """

    def __init__(self, params: DeviceParams) -> None:
        self.task = params.task
        self.realism = params.realism
        m = params.task.dim
        r = params.realism
        self._quant = r.quantization if r.quantization.size else np.zeros(m)
        self._noise = r.noise_std if r.noise_std.size else np.zeros(m)
        self._has_noise = bool(np.any(self._noise))
        self._has_quant = bool(np.any(self._quant))
        self._rng = np.random.default_rng(r.seed)
        self._last: np.ndarray | None = None
        self._velocity = np.zeros(m)

    def measure(self, pose: np.ndarray, twist: np.ndarray,
                dt: float) -> tuple[np.ndarray, np.ndarray]:
        r = self.realism
        x = np.array(pose, dtype=float)
        if self._has_noise:
            x = x + self._noise * self._rng.standard_normal(x.size)
        q = self._quant
        if self._has_quant:
            x = np.where(q > 0.0, np.round(x / np.where(q > 0.0, q, 1.0)) * q, x)
        if r.velocity is VelocitySource.MODEL:
            return x, np.array(twist, dtype=float)
        if self._last is not None and dt > 0.0:
            raw = pose_difference(x, self._last, self.task) / dt
            a = (1.0 if r.velocity_cutoff_hz <= 0.0
                 else 1.0 - math.exp(-2.0 * math.pi * r.velocity_cutoff_hz * dt))
            self._velocity = self._velocity + a * (raw - self._velocity)
        self._last = x
        return x, self._velocity.copy()
