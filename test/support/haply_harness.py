"""Test helpers of the ``haply`` backend: the Haply Inverse Service emulator
(``python -m haptic_topology.remote.haply_emulator``) in a process of its own, and that process
as a conformance :class:`backend_conformance.DeviceSide`.

:class:`Emulator` starts it (``--port 0`` unless a port is given: a restarted service comes
back where it was) and waits for its ready file; the process handling is
``service_process.py``'s, shared with the network backend's device server. Its ``--log`` (one
line per command received) is read once it has stopped; its ``--monitor`` stream (a UDP copy
of each log line as it happens) is what :class:`EmulatorDevice` watches.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from service_process import MonitoredDevice, ServiceProcess


def read_log(path: Path) -> tuple[np.ndarray, list[str], np.ndarray]:
    """The emulator's ``--log``: monotonic ns, device id, force (n x 3, N, device frame)."""
    t, ids, f = [], [], []
    for line in path.read_text(encoding='utf-8').splitlines():
        ns, dev, x, y, z = line.split(',')
        t.append(int(ns))
        ids.append(dev)
        f.append((float(x), float(y), float(z)))
    return np.array(t, dtype=np.int64), ids, np.array(f).reshape(-1, 3)


class Emulator(ServiceProcess):
    """The emulated service in its own process (module doc); ``extra``: more arguments;
    ``port``: 0 for any free one; ``monitor``: where to send the ``--monitor`` copies."""

    def __init__(self, tmp: Path, extra: tuple[str, ...] = (), tag: str = 'haply',
                 monitor: tuple[str, int] | None = None, port: int = 0) -> None:
        self.log = tmp / f'{tag}.log.csv'
        self.log.unlink(missing_ok=True)
        args = ['--port', str(port), '--log', str(self.log), *extra]
        if monitor is not None:
            args += ['--monitor', f'{monitor[0]}:{monitor[1]}']
        super().__init__('haptic_topology.remote.haply_emulator', args, tmp, tag,
                         'the Haply emulator')


class EmulatorDevice(MonitoredDevice):
    """The emulator process as a conformance ``DeviceSide`` for a task of dimension ``m``
    mapped with the default axes (task x, y, z = device x, y, z): ``log`` stops it and reads
    its log (the forces as task vectors). :meth:`restart` replaces the process by a new one
    on the same port (the service restarted), watched by the same monitor."""

    def __init__(self, tmp: Path, m: int, extra: tuple[str, ...] = ()) -> None:
        super().__init__()
        self.m = m
        self.service = self.emulator = Emulator(tmp, (*self.monitor_arg, *extra))
        self.port = self.emulator.port

    def take(self, data: bytes) -> tuple[int, np.ndarray]:
        ns, _, x, y, z = data.decode().split(',')
        return int(ns), np.array([float(x), float(y), float(z)])[:self.m]

    def restart(self, tmp: Path, extra: tuple[str, ...] = ()) -> Emulator:
        """Kill the emulator (if it runs) and start another on the same port with ``extra``."""
        self.emulator.kill()
        self.service = self.emulator = Emulator(tmp, (*self.monitor_arg, *extra),
                                                port=self.port)
        return self.emulator

    def log(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.stopped:
            self.stopped = True
            self.emulator.stop()
        t, _, f = read_log(self.emulator.log)
        return t, f[:, :self.m]
