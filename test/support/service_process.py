"""What the tests of the backends of a device behind a process of its own share: the device
server of the ``network`` backend (``network_harness.py``) and the Haply Inverse Service
emulator of the ``haply`` backend (``haply_harness.py``).

* :class:`ServiceProcess`: ``python -m <module> <args> --ready-file F`` in a process of its
  own, ready once ``F`` exists (the JSON the service writes there, :attr:`~ServiceProcess.info`;
  no output is parsed); :meth:`~ServiceProcess.stop` sends SIGINT and waits,
  :meth:`~ServiceProcess.kill` sends SIGKILL (a crash);
* :class:`MonitoredDevice`: such a process as a conformance
  :class:`backend_conformance.DeviceSide`, watched through its ``--monitor HOST:PORT`` stream
  (one UDP datagram per wrench it got, stamped with the monotonic clock of this machine):
  ``poll`` takes what has come, ``got`` looks at the newest;
* :func:`made_devices`: the body of a fixture that makes device sides and closes them at
  the test's end; :func:`paced`: one device cycle per millisecond of wall time, for a device
  on its own clock.
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from backend_conformance import same

from haptic_topology.device.pacing import DeadlinePacer

REPO = Path(__file__).resolve().parents[2]
#: Longest wait (s) for a service to write its ready file.
READY_WAIT = 120.0


class ServiceProcess:
    """``python -m module *args --ready-file <tmp>/<tag>.ready.json`` (module doc); ``what``
    names it in failures."""

    def __init__(self, module: str, args: list[str], tmp: Path, tag: str, what: str) -> None:
        tmp.mkdir(parents=True, exist_ok=True)
        self.what = what
        self.ready = tmp / f'{tag}.ready.json'
        self.ready.unlink(missing_ok=True)
        self.output = ''
        cmd = [sys.executable, '-m', module, *args, '--ready-file', str(self.ready)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     cwd=REPO, env=dict(os.environ))
        deadline = time.monotonic() + READY_WAIT
        while not self.ready.exists():
            if self.proc.poll() is not None:
                out = self.proc.communicate()[0].decode(errors='replace')
                raise AssertionError(f'{what} ended with {self.proc.returncode}: {out}')
            if time.monotonic() > deadline:
                self.kill()
                raise AssertionError(f'{what} not ready within {READY_WAIT:g} s')
            time.sleep(0.02)
        #: What the service wrote to its ready file (its port, ...).
        self.info: dict[str, Any] = json.loads(self.ready.read_text())
        self.port = int(self.info['port'])

    @property
    def running(self) -> bool:
        return self.proc.poll() is None

    def kill(self) -> None:
        """SIGKILL (a crash: what it would write at its end is lost) if still running, and
        its output."""
        if self.proc.poll() is None:
            self.proc.kill()
        if self.proc.stdout is not None and not self.proc.stdout.closed:
            self.output = self.proc.communicate()[0].decode(errors='replace')

    def stop(self, timeout: float = 30.0) -> str:
        """SIGINT (if still running), wait at most ``timeout`` s; its output."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            out = self.proc.communicate(timeout=timeout)[0]
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out = self.proc.communicate()[0]
            raise AssertionError(f'{self.what} did not stop on SIGINT within {timeout:g} s: '
                                 f'{out.decode(errors="replace")}') from None
        self.output = out.decode(errors='replace')
        return self.output


class MonitoredDevice:
    """A device process as a conformance ``DeviceSide`` (module doc). A subclass starts the
    process with :attr:`monitor_arg` among its arguments, sets :attr:`service`, and says how to
    read one datagram (:meth:`take`) and the process's own log (:meth:`log`)."""

    def __init__(self) -> None:
        self.monitor = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.monitor.bind(('127.0.0.1', 0))
        self.monitor.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        #: ``--monitor HOST:PORT`` for the process.
        self.monitor_arg = ['--monitor', f'127.0.0.1:{self.monitor.getsockname()[1]}']
        #: The newest wrench the device got: (monotonic ns, the wrench as a task vector).
        self.newest: tuple[int, np.ndarray] | None = None
        #: Whether the process was stopped on purpose (its end is then no failure).
        self.stopped = False
        self.service: ServiceProcess

    def take(self, data: bytes) -> tuple[int, np.ndarray] | None:
        """One monitor datagram as (monotonic ns, wrench), None to pass it over."""
        raise NotImplementedError

    def after_cycle(self, backend: object) -> None:
        pass

    def poll(self, seconds: float) -> None:
        """Take every datagram that has come, waiting up to ``seconds`` for the first."""
        wait = seconds
        while select.select([self.monitor], [], [], wait)[0]:
            got = self.take(self.monitor.recv(65536))
            if got is not None and (self.newest is None or got[0] >= self.newest[0]):
                self.newest = got
            wait = 0.0
        if not self.service.running and not self.stopped:
            raise AssertionError(f'{self.service.what} exited ({self.service.proc.returncode})')

    def got(self, expected: np.ndarray, after_ns: int) -> bool:
        st = self.newest
        return st is not None and st[0] >= after_ns and same(st[1], expected)

    def close(self) -> None:
        """Kill the process if it still runs; close the monitor."""
        self.service.kill()
        self.monitor.close()


D = TypeVar('D', bound=MonitoredDevice)


def made_devices(tmp: Path, make: Callable[[Path, str], D]) -> Iterator[Callable[[str], D]]:
    """A fixture's body: yields ``factory(scenario)``, which calls ``make(folder, scenario)``
    with a fresh folder under ``tmp`` each time; every device made is closed at the end."""
    made: list[D] = []

    def factory(scenario: str) -> D:
        dev = make(tmp / f'd{len(made)}', scenario)
        made.append(dev)
        return dev

    yield factory
    for dev in made:
        dev.close()


def paced(period: float = 0.001) -> Callable[[], None]:
    """A ``Subject.pace``: each call returns at the next deadline ``period`` s apart."""
    pacer = DeadlinePacer(period)
    return lambda: None if pacer.wait() else None
