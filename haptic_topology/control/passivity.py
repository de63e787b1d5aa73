"""Energy at the device port and time-domain passivity (Hannaford & Ryu) of the control law.

Every :class:`~haptic_topology.control.controller.HapticController` keeps an
:class:`EnergyAccount`: once per answered device state it adds up, over the period that has
just ended, the energy its command put into the device port, per axis, in total and per part
of the command, and the passivity observer. The arithmetic is compiled
(:mod:`haptic_topology.control.energy`, in the same call as the law of eq. 14 / eq. 10), so the
offline simulation, the lock-step graph and the wall-clock loop account alike.

**Sign convention.** *Work* ``W = sum_k u_(k-1) . (x_k (-) x_(k-1))`` (J) is the energy the
controller puts into the device: the wrench it commanded for a period (clamped to the
device's wrench limit, as the device applies it) times the displacement over that period,
i.e. ``sum F v dT`` with ``v dT`` measured as a displacement, which is the exact work of a
wrench held over the period. Positive work drives the device. The device's own damping
``C_d`` of eq. 9 dissipates ``D = sum dx . C_d v``. The **passivity observer** is
``E = D - (W - W_hand) + W_vt``: the energy the law has taken in since the run began, with
the work of the ``hand`` part ``W_hand`` left out and the VT's end ``W_vt`` counted (below).
A passive law keeps ``E >= 0``.

**Two ports.** The coupling parts of a command (``penalty``, ``coordination``,
``contacts``) are a spring and damper between two ends: the device's hand and the LMI's VT
hand (``e = x_vt (-) x_h``, eqs. 13, 15-16). Energy enters such a coupling at the VT's end as
well as at the device's: when the VT moves (pushed by the hand through the VE, eq. 17), the
coupling pulls the device after it and hands the device energy that the VE gave it, not energy
the law generated; and what the coupling holds between its two ends is stored, not generated.
So the observer counts, for these parts, the work done at both ends: at the device's
``u_c . dx`` (out of the law) and at the VT's ``W_vt = sum u_c . xd_vt dT`` (into it), the VT's
motion over the period as the LMI integrates it (``xd_vt`` after the LMI's semi-implicit
step, the period ``dT``). What the coupling then generates is what a sampled law adds on top
(the held command lagging the motion, Colgate & Schenkel) and what a re-sync of the LMI to the
VE injects: a re-sync moves the VT's end with no work counted at it (its jump is left out of
``W_vt``), so the energy it puts into the coupling shows as generated when the coupling gives it
to the device. With the VT at rest (a wall, a constrained direction) the observer is the
device port's one-port observer.

**Parts** of a command (their work adds up to ``W`` while no clamp cuts the command):
``penalty`` ``M_d P (k_tc e + b_tc edot)`` (eq. 13), ``coordination`` ``M_d L F_pc``
(eqs. 10, 15-16), ``contacts`` ``M_d L F_env``, ``damping`` ``C_d xd_h`` (eq. 10's
compensation of the device damping), ``hand`` ``(M_d L - I) F_h`` (eq. 10's inertia
shaping) and ``passivity`` (the controller below; its work is <= 0).

**Passivity controller** (:class:`PassivityConfig`, off unless configured): Hannaford & Ryu's
one-port controller at the controller's rate, for the sampled loop with the LMI. It watches the
*windowed observer* ``E_w``: the sum of the newest ``window`` seconds of the observer's
increments (older dissipated energy is forgotten, so the law cannot stay passive on credit
earned long ago). The hand part is left out of the observer: it is a
feed-forward of the measured hand wrench that makes the device's inertia feel like the VT's
(eq. 10): the energy it moves goes to and comes back from the device's kinetic energy while the
user accelerates a VT lighter than the device, so counting it would damp the rendering itself;
the energy a sampled, delayed or too stiff law *generates* is in the feedback parts (penalty,
coordination, contacts, damping). When ``E_w < 0`` it adds the damping ``-alpha xd_h`` to the
command held over the next period, with ``alpha = -E_w / (dT max(|xd_h|^2, v_floor^2))`` (the
floor keeps ``alpha`` finite at rest), at most ``damping_max``, the added wrench clipped to
the wrench limit on each axis (an axis moving fast against a small limit, a rotation, does
not lower the damping of the others; the clipped damper still only dissipates). It acts on the
total observer of the port, not per axis: energy the law moves between axes is not generated.
The observer counts the command as the device applies it one period later, so the energy the
damping dissipates is measured, not assumed; the delay of a VE update (the LMI's 100 or 25 Hz)
and of two hosts lies inside the controller's one-port, which is what the observer watches.
See ``docs/concepts/control.md``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from haptic_topology.errors import ConfigError
from haptic_topology.validate import as_float, check_keys

#: Names of the parts of a command, in the account's order (module doc).
PARTS = ('penalty', 'coordination', 'contacts', 'damping', 'hand', 'passivity')
_N_PARTS = len(PARTS)
# The state vector's head (haptic_topology.control.energy).
(_HAVE, _WORK, _DISSIPATED, _OBSERVER, _WINDOWED, _ALPHA, _ACTED, _PEAK, _MINIMUM, _RING,
 _VT_WORK) = range(11)
_HEAD = 11
_PARAMS = 4             # after the head: PC on, |v|^2 floor, damping cap, window; the limit


@dataclass(frozen=True)
class PassivityConfig:
    """The passivity controller's settings (module doc). ``enabled``; ``velocity_floor``
    (m/s or rad/s): the floor of ``|xd_h|`` in ``alpha``; ``damping_max`` (N s/m, N m s/rad;
    None: the device's smallest inertia over the period, ``min eig(M_d) / dT``, half of
    what a held damper on that inertia stands); ``window`` (s; 0: never forget)."""

    enabled: bool = False
    velocity_floor: float = 1e-3
    damping_max: float | None = None
    window: float = 1.0

    @classmethod
    def from_config(cls, raw: Any, where: str, default_enabled: bool = False
                    ) -> PassivityConfig:
        """A ``passivity:`` block: ``enabled`` (bool), ``velocity_floor`` (> 0),
        ``damping_max`` (> 0), ``window`` (s, >= 0); None: the defaults."""
        if raw is None:
            return cls(enabled=default_enabled)
        c = check_keys(raw, where, optional=('enabled', 'velocity_floor', 'damping_max',
                                             'window'))
        enabled = c.get('enabled', default_enabled)
        if not isinstance(enabled, bool):
            raise ConfigError(f'{where}.enabled: expected true or false, got {enabled!r}')
        dmax = c.get('damping_max')
        return cls(enabled=enabled,
                   velocity_floor=as_float(c.get('velocity_floor', 1e-3),
                                           f'{where}.velocity_floor', lo=1e-9),
                   damping_max=(None if dmax is None
                                else as_float(dmax, f'{where}.damping_max', lo=1e-9)),
                   window=as_float(c.get('window', 1.0), f'{where}.window', lo=0.0))


class EnergyAccount:
    """The energy account and passivity controller of one controller (module doc), for a
    task of dimension ``m``, nominal period ``dt`` (s) and device inertia ``mass`` (m x m).

    ``state`` is the one array :func:`~haptic_topology.control.energy.account` works on: a
    head of figures, the parameters (:attr:`params`), the wrench limit (:attr:`limit`; N,
    N m, inf until :meth:`set_limit`), the previous pose and command, the work per axis and
    per part, the previous command's parts, the window's ring."""

    def __init__(self, m: int, config: PassivityConfig, dt: float, mass: np.ndarray) -> None:
        self.m = m
        self.config = config
        window = int(round(config.window / dt)) if config.window > 0.0 and dt > 0.0 else 0
        dmax = config.damping_max
        if dmax is None:
            low = float(np.linalg.eigvalsh(0.5 * (mass + mass.T)).min())
            dmax = low / dt if dt > 0.0 else math.inf
        self._at = _HEAD + _PARAMS + m          # where the previous pose starts
        self.state = np.zeros(self._at + 3 * m + _N_PARTS + _N_PARTS * m + window)
        self.params[:] = (1.0 if config.enabled else 0.0, config.velocity_floor ** 2, dmax,
                          float(window))
        self.limit[:] = np.inf
        self.first_acted: float | None = None      # loop time (s) the PC first acted
        self.last_acted: float | None = None

    @property
    def params(self) -> np.ndarray:
        """The parameters in ``state`` (a view): PC on (1/0), the floor of ``|v|^2``,
        the damping cap, the window (cycles)."""
        return self.state[_HEAD:_HEAD + _PARAMS]

    @property
    def limit(self) -> np.ndarray:
        """The wrench limit in ``state`` (a view; N, N m)."""
        return self.state[_HEAD + _PARAMS:_HEAD + _PARAMS + self.m]

    def enable(self, on: bool) -> None:
        """Switch the passivity controller on or off (between two cycles)."""
        self.params[0] = 1.0 if on else 0.0

    def set_limit(self, limit: np.ndarray) -> None:
        """The device's wrench limit (N, N m, m values): commands are accounted clamped."""
        self.limit[:] = np.asarray(limit, dtype=float)

    # -- what the loop tells the account ------------------------------------------------------
    def break_period(self) -> None:
        """No command of the law was held over the period now running (an unsynced or idle
        cycle): the next state starts a new period, this one is not accounted."""
        self.state[_HAVE] = 0.0

    def scaled(self, scale: float, sent: np.ndarray) -> None:
        """The loop sent ``sent`` (``scale`` times the law's command, the sync guard's fade)
        in place of the command accounted."""
        m = self.m
        s = self.state
        s[self._at + m:self._at + 2 * m] = np.clip(sent, -self.limit, self.limit)
        at = self._at + 3 * m + _N_PARTS
        s[at:at + _N_PARTS * m] *= scale

    def note(self, now: float) -> None:
        """After a cycle at loop time ``now`` (s): when the passivity controller acted."""
        if self.state[_ALPHA] > 0.0:
            if self.first_acted is None:
                self.first_acted = now
            self.last_acted = now

    # -- figures ------------------------------------------------------------------------------
    @property
    def work(self) -> float:
        """W (J): energy the controller put into the device port (module doc)."""
        return float(self.state[_WORK])

    @property
    def work_axis(self) -> np.ndarray:
        """W per task axis (J; m values)."""
        m = self.m
        return self.state[self._at + 2 * m:self._at + 3 * m].copy()

    @property
    def work_parts(self) -> dict[str, float]:
        """W per part of the command (J; :data:`PARTS`)."""
        at = self._at + 3 * self.m
        return dict(zip(PARTS, (float(v) for v in self.state[at:at + _N_PARTS]), strict=True))

    @property
    def vt_work(self) -> float:
        """W_vt (J): the work of the coupling parts at the VT's end (module doc)."""
        return float(self.state[_VT_WORK])

    @property
    def dissipated(self) -> float:
        """D (J): energy the device damping ``C_d`` dissipated."""
        return float(self.state[_DISSIPATED])

    @property
    def observer(self) -> float:
        """E = D - W + W_hand + W_vt (J), the passivity observer."""
        return float(self.state[_OBSERVER])

    @property
    def windowed(self) -> float:
        """E_w (J): the observer over the newest window (the controller's)."""
        return float(self.state[_WINDOWED])

    @property
    def damping(self) -> float:
        """alpha (N s/m, N m s/rad) added to the newest command (0: none)."""
        return float(self.state[_ALPHA])

    def summary(self) -> dict[str, Any]:
        """The account's figures for ``summary.json`` (J, N s/m, s of loop time)."""
        s = self.state
        return {
            'port_work_j': self.work,
            'port_work_axis_j': [float(v) for v in self.work_axis],
            'port_work_parts_j': self.work_parts,
            'device_damping_dissipated_j': self.dissipated,
            'vt_work_j': self.vt_work,
            'passivity_observer_j': self.observer,
            'passivity_observer_min_j': float(s[_MINIMUM]),
            'passivity_controller': bool(self.params[0]),
            'passivity_cycles': int(s[_ACTED]),
            'passivity_dissipated_j': -self.work_parts['passivity'],
            'passivity_damping_max': float(s[_PEAK]),
            'passivity_first_s': self.first_acted,
            'passivity_last_s': self.last_acted,
        }

    def values(self) -> dict[str, str]:
        """Diagnostics key/values (the live channel): the figures rounded for reading, and
        ``energy_account``, :meth:`summary` as JSON (floats exact), which a recorded run's
        analysis reads from the controller's last status
        (``haptic_topology.bag.analyze.controller_account``)."""
        s = self.state
        return {
            'port_work_j': f'{self.work:.6g}',
            'port_work_axis_j': ' '.join(f'{v:.4g}' for v in self.work_axis),
            **{f'work_{k}_j': f'{v:.4g}' for k, v in self.work_parts.items()},
            'vt_work_j': f'{self.vt_work:.6g}',
            'passivity_observer_j': f'{self.observer:.6g}',
            'passivity_observer_min_j': f'{float(s[_MINIMUM]):.6g}',
            'passivity_windowed_j': f'{self.windowed:.6g}',
            'passivity_controller': 'on' if self.params[0] else 'off',
            'passivity_cycles': str(int(s[_ACTED])),
            'passivity_damping': f'{self.damping:.4g}',
            'energy_account': json.dumps(self.summary()),
        }
