"""The simulated maglev as a device on its own clock: what ``topic_device`` plays (no ROS).

:class:`DevicePlayer` takes commands as they arrive (:meth:`DevicePlayer.command`, any
thread) and steps the ``sim_maglev`` physics (eq. 9, with the scenario's simulated user) once
per device cycle (:meth:`DevicePlayer.cycle`, its loop thread): the newest command, clamped
to the device's wrench limit, or zero when it is older than the command timeout or not
finite (a real device's own timeout and saturation).

The device is parked (its pose held, the hand not pushing) until a driver engages it. With
a force sensor topic (``hand_published``) that is the first non-zero command: the
controller sees the hand's wrench and answers it. Without one the hand's wrench never
reaches the controller, as on a device without a force sensor, so nothing would ever be
non-zero: the simulated hand then pushes from the first command on (a driver commands zero
while it idles), and the controller answers the motion.
"""

from __future__ import annotations

import numpy as np

from haptic_topology.device.backend import BackendConfig, DeviceReading, SimMaglevBackend
from haptic_topology.device.maglev import saturate


class DevicePlayer:
    """The played device configured with ``config`` (the ``sim_maglev`` backend's: the
    scenario's device, its initial pose and user), ``timeout_ns`` its command timeout (ns),
    ``hand_published``: whether the hand's wrench is published (module doc: when the device
    unparks)."""

    def __init__(self, config: BackendConfig, timeout_ns: int, hand_published: bool) -> None:
        self.limit = np.asarray(config.params.wrench_limit, dtype=float)
        self.sim = SimMaglevBackend()
        self.sim.configure(config)
        self.sim.activate()
        self.timeout_ns = timeout_ns
        self.push_from_first_command = not hand_published
        #: The newest command: (arrival ns, task wrench or None when not finite).
        self.newest: tuple[int, np.ndarray | None] | None = None
        self.commands = self.nonfinite_commands = self.nonzero_commands = 0
        self.max_abs_command = np.zeros(self.limit.size)
        self.cycles = self.timeout_cycles = 0
        self.engaged = False

    def command(self, now_ns: int, u: np.ndarray | None) -> None:
        """A command (task wrench, N and N m; None: not finite) arrived at ``now_ns``."""
        self.commands += 1
        if u is None:
            self.nonfinite_commands += 1
        else:
            np.maximum(self.max_abs_command, np.abs(u), out=self.max_abs_command)
            if np.any(u != 0.0):
                self.nonzero_commands += 1
        self.newest = (now_ns, u)

    def cycle(self, now_ns: int, dt: float) -> DeviceReading:
        """One device cycle at ``now_ns``, ``dt`` s after the previous one."""
        cmd = self.newest
        u = np.zeros(self.limit.size)
        if cmd is not None and cmd[1] is not None and now_ns - cmd[0] <= self.timeout_ns:
            u = saturate(cmd[1], self.limit)[0]
        elif cmd is not None:
            self.timeout_cycles += 1
        if not self.engaged and (np.any(u != 0.0)
                                 or (self.push_from_first_command and cmd is not None)):
            self.engaged = True
        self.cycles += 1
        if not self.engaged:
            return self.sim.idle(dt)
        self.sim.write(u)
        return self.sim.read(dt)
