"""Test helpers of the ``haply`` backend: the Haply Inverse Service emulator
(``python -m haptic_topology.remote.haply_emulator``) in a process of its own, and that process
as a conformance :class:`backend_conformance.DeviceSide`.

:class:`Emulator` starts it with ``--port 0`` and waits for its ready file (no output is
parsed); :meth:`Emulator.stop` sends SIGINT and reads its per-command log (``--log``). Its
``--monitor`` stream (a UDP copy of each log line as it happens) is what ``got`` looks at.
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
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]


def read_log(path: Path) -> tuple[np.ndarray, list[str], np.ndarray]:
    """The emulator's ``--log``: monotonic ns, device id, force (n x 3, N, device frame)."""
    t, ids, f = [], [], []
    for line in path.read_text(encoding='utf-8').splitlines():
        ns, dev, x, y, z = line.split(',')
        t.append(int(ns))
        ids.append(dev)
        f.append((float(x), float(y), float(z)))
    return np.array(t, dtype=np.int64), ids, np.array(f).reshape(-1, 3)


class Emulator:
    """The emulated service in its own process (module doc); ``extra``: more arguments."""

    def __init__(self, tmp: Path, extra: tuple[str, ...] = (), tag: str = 'haply',
                 monitor: tuple[str, int] | None = None) -> None:
        tmp.mkdir(parents=True, exist_ok=True)
        self.ready = tmp / f'{tag}.ready.json'
        self.log = tmp / f'{tag}.log.csv'
        for p in (self.ready, self.log):
            p.unlink(missing_ok=True)
        cmd = [sys.executable, '-m', 'haptic_topology.remote.haply_emulator', '--port', '0',
               '--ready-file', str(self.ready), '--log', str(self.log), *extra]
        if monitor is not None:
            cmd += ['--monitor', f'{monitor[0]}:{monitor[1]}']
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     cwd=REPO, env=dict(os.environ))
        deadline = time.monotonic() + 120.0
        while not self.ready.exists():
            if self.proc.poll() is not None:
                out = self.proc.communicate()[0].decode(errors='replace')
                raise AssertionError(f'emulator ended with {self.proc.returncode}: {out}')
            if time.monotonic() > deadline:
                self.kill()
                raise AssertionError('emulator not ready within 120 s')
            time.sleep(0.02)
        info = json.loads(self.ready.read_text())
        self.port = int(info['port'])
        self.output = ''

    def kill(self) -> None:
        """SIGKILL (if still running: its log is lost), and its output."""
        if self.proc.poll() is None:
            self.proc.kill()
        if self.proc.stdout is not None and not self.proc.stdout.closed:
            self.output = self.proc.communicate()[0].decode(errors='replace')

    def stop(self, timeout: float = 30.0) -> str:
        """SIGINT (if still running), wait; its output."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            out = self.proc.communicate(timeout=timeout)[0]
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out = self.proc.communicate()[0]
            raise AssertionError(f'emulator did not stop on SIGINT: {out!r}') from None
        self.output = out.decode(errors='replace')
        return self.output


class EmulatorDevice:
    """The emulator process as a conformance ``DeviceSide`` for a task of dimension ``m``
    mapped with the default axes (task x, y, z = device x, y, z): ``poll`` takes its
    monitor stream, ``got`` looks at the newest force it got, ``log`` stops it and reads its
    log (the forces as task vectors)."""

    def __init__(self, tmp: Path, m: int, extra: tuple[str, ...] = ()) -> None:
        self.m = m
        self.monitor = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.monitor.bind(('127.0.0.1', 0))
        self.monitor.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.emulator = Emulator(tmp, extra, monitor=('127.0.0.1',
                                                      self.monitor.getsockname()[1]))
        self.port = self.emulator.port
        self.newest: tuple[int, np.ndarray] | None = None
        self.stopped = False

    def after_cycle(self, backend: object) -> None:
        pass

    def poll(self, seconds: float) -> None:
        wait = seconds
        while select.select([self.monitor], [], [], wait)[0]:
            ns, _, x, y, z = self.monitor.recv(4096).decode().split(',')
            self.newest = (int(ns), np.array([float(x), float(y), float(z)])[:self.m])
            wait = 0.0
        if self.emulator.proc.poll() is not None and not self.stopped:
            raise AssertionError(f'emulator exited ({self.emulator.proc.returncode})')

    def got(self, expected: np.ndarray, after_ns: int) -> bool:
        st = self.newest
        return (st is not None and st[0] >= after_ns
                and bool(np.all(np.abs(st[1] - expected) <= 1e-12 * (1.0 + np.abs(expected)))))

    def log(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.stopped:
            self.stopped = True
            self.emulator.stop()
        t, _, f = read_log(self.emulator.log)
        return t, f[:, :self.m]

    def close(self) -> None:
        if self.emulator.proc.poll() is None:
            self.emulator.kill()
        self.monitor.close()
