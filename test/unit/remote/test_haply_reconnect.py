"""The ``haply`` backend's reconnection after a lost connection to the Haply Inverse Service
(``haptic_topology.remote.haply``, "A lost connection"), against the emulator in a process of
its own, killed and started again on the same port mid-run: the sequence of the readings
(grasping; FAULT, connection lost, reconnecting; FAULT, reconnected, waiting for a re-grasp;
the re-grasp's fade-in; grasping), nothing but zero written or sent from the loss to the
re-grasp, then the force fading in; the backoff of the attempts (on an injected clock); an
attempt whose handshake never ends never holds a cycle; ``reconnect_max_ms: 0``. Waits are
on conditions with deadlines; no timing is asserted."""

from __future__ import annotations

import re
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from backend_conformance import Bench, Subject
from haply_harness import EmulatorDevice, read_log

from haptic_topology.device.backend import BackendConfig
from haptic_topology.remote.haply import HaplyBackend
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import DeviceStatus

FAULT = DeviceStatus.FAULT
WAIT = 60.0
GRIP = ('--grip', '61548')
#: The force the loop is asked for (task = device frame, N) and its norm.
U = np.array([1.5, -1.0])
FULL = float(np.hypot(*U))


def _label(status: DeviceStatus, reason: str) -> str:
    """What a state says: ``grasp`` (OK), ``fade`` (WATCHDOG: the grasp or the driver's output
    fading in), ``lost`` (FAULT, the connection ended), ``rejoin`` (FAULT, reconnected)."""
    if not status & FAULT:
        return 'grasp' if status == DeviceStatus.OK else 'fade'
    if 'reconnected to' in reason:
        return 'rejoin'
    return 'lost' if 'ended' in reason else f'other fault: {reason}'


def _runs(labels: list[str]) -> list[str]:
    return [a for k, a in enumerate(labels) if k == 0 or labels[k - 1] != a]


class Run:
    """A bench on the emulator (``extra``: its arguments) cycling with the constant force
    :data:`U`, recording each reading's label and the fault reason."""

    def __init__(self, tmp: Path, extra: tuple[str, ...], **options: Any) -> None:
        self.device = EmulatorDevice(tmp / 'e0', 2, extra)
        opts = {'port': self.device.port, 'stale_ms': 2000.0, **options}
        self.bench = Bench(Subject('haply', lambda: self.device, opts, 'fig8_point'),
                           self.device)
        self.backend = self.bench.backend
        assert isinstance(self.backend, HaplyBackend)
        self.labels: list[str] = []
        self.reasons: list[str] = []
        self.bench.activate()
        self.bench.engage()

    def cycle(self) -> None:
        st = self.bench.cycle(U).status
        reason = self.backend.fault_reason() if st & FAULT else ''
        self.labels.append(_label(st, reason))
        self.reasons.append(reason)
        time.sleep(0.0005)

    def until(self, cond: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + WAIT
        while not cond():
            assert time.monotonic() < deadline, f'never {what}: {_runs(self.labels)}'
            self.cycle()


def test_the_service_restarted_mid_run(tmp_path: Path) -> None:
    """Engage button 0 (the grip's a), held from the start: the hand grasps. The service is
    killed: FAULT, reconnecting (refused while it is down). It comes back without the device
    (still FAULT: not in its inventory), then with it, the button still held (messages 1-20):
    FAULT, reconnected, and the held button does not grasp; released (21-59) and pressed
    again (60 on): the force fades in, from zero to the command, never a jump."""
    run = Run(tmp_path, (*GRIP, '--press', 'a@1-100000000'), engage_button=0,
              grasp_ramp_ms=20.0, max_in_flight=64, reconnect_max_ms=200.0)
    backend, device = run.backend, run.device
    run.until(lambda: run.labels[-1:] == ['grasp'], 'grasping')
    assert backend.link() == 'up'
    device.emulator.kill()
    run.until(lambda: 'Connection refused' in run.reasons[-1], 'refused while down')
    assert backend.link().startswith('down, reconnecting: cannot connect to ws://127.0.0.1:')
    device.restart(tmp_path / 'e1', (*GRIP, '--device', '0000'))
    run.until(lambda: 'is not in the inventory' in run.reasons[-1], 'the wrong device seen')
    assert run.reasons[-1].endswith('the Inverse3 0E31 is not in the inventory (it has 0000))')
    second = device.restart(tmp_path / 'e2', (*GRIP, '--press', 'a@1-20', '--press',
                                              'a@60-100000000'))
    run.until(lambda: run.labels[-1] == 'rejoin', 'reconnected')
    assert backend.link() == 'up, waiting for a re-engage'
    run.until(lambda: run.labels[-1] == 'grasp', 'grasping again')
    for _ in range(20):
        run.cycle()
    values = backend.values()
    assert (backend.link(), backend.reconnects, values['grasps']) == ('up', 1, '2')
    lost, rejoin = run.labels.index('lost'), run.labels.index('rejoin')
    back = run.labels.index('fade', rejoin)
    assert run.reasons[rejoin].startswith(
        f'haply: reconnected to ws://127.0.0.1:{device.port}/ after the connection ended (')
    assert run.reasons[back - 1].endswith('release and press the engage button (button 0) to '
                                          'grasp again'), run.reasons[back - 1]
    # the sequence of the readings: grasping; lost (reconnecting); reconnected; the re-grasp
    # fading in; grasping (a first fade at the start may have ended in the idle cycles)
    runs = _runs(run.labels)
    assert runs[runs.index('grasp'):] == ['grasp', 'lost', 'rejoin', 'fade', 'grasp'], runs
    # the loop wrote zero from the cycle after the loss to the re-grasp's reading
    w = np.array(run.bench.written)
    assert w[:lost].any() and not w[lost + 1:back + 1].any()
    run.bench.release()
    device.stopped = True
    second.stop()
    device.close()
    # what the restarted service got: zero up to the press (message 60) at least, then the
    # force fading in (growing, never past the command) to the command
    _, ids, f = read_log(second.log)
    norm = np.hypot(f[:, 0], f[:, 1])
    on = np.flatnonzero(norm > 0.0)
    assert set(ids) == {'0E31'} and on.size and on[0] >= 60, on[:3]
    full = int(np.flatnonzero(np.abs(norm - FULL) <= 1e-12)[0])
    rise = norm[on[0]:full + 1]
    assert 0.0 < rise[0] < FULL and np.all(np.diff(rise) >= 0.0), rise
    assert np.allclose(f[on[0]:full + 1, :2] / rise[:, None], U / FULL, rtol=0, atol=1e-12)


def test_without_buttons_the_fault_stands_until_the_next_activation(tmp_path: Path) -> None:
    """No engage or clutch button: once reconnected the reading stays FAULT, its reason says
    so, and the restarted service gets nothing but zero; a new activation grasps."""
    run = Run(tmp_path, (), grasp_ramp_ms=0.0, reconnect_max_ms=200.0)
    backend, device = run.backend, run.device
    run.until(lambda: run.labels[-1:] == ['grasp'], 'grasping')
    device.emulator.kill()
    run.until(lambda: run.labels[-1] == 'lost', 'lost')
    second = device.restart(tmp_path / 'e1')
    run.until(lambda: run.labels[-1] == 'rejoin' and backend.states > backend._rejoin_states
              + 50, 'states again')
    assert run.reasons[-1].endswith('no engage or clutch button is configured: forces resume '
                                    'at the next activation of device_driver')
    assert _runs(run.labels)[-3:] == ['grasp', 'lost', 'rejoin']
    run.bench.release()
    mark = time.monotonic_ns()
    run.bench.activate()
    run.bench.engage()
    run.labels.clear()
    run.until(lambda: run.labels[-1:] == ['grasp'], 'grasping after a new activation')
    run.bench.release()
    device.stopped = True
    second.stop()
    device.close()
    t, _, f = read_log(second.log)
    assert np.count_nonzero(t < mark) > 50 and not f[t < mark].any()
    assert f[t >= mark].any()


def _configured(options: dict[str, Any], clock_ns: Callable[[], int]) -> HaplyBackend:
    sc = load_scenario('fig8_point')
    b = HaplyBackend(clock_ns)
    b.configure(BackendConfig(sc.device, initial_device_pose(sc), {}, options, sc.source))
    return b


def test_attempts_back_off_to_reconnect_max_ms(tmp_path: Path) -> None:
    """On an injected clock, 1 ms a cycle, the service gone for 10 s: attempts at 50, 150,
    350, 750, 1550, 3150 ms, then every 2000 ms (5150, 7150, 9150): nine, each refused."""
    now = [time.monotonic_ns()]
    device = EmulatorDevice(tmp_path / 'e0', 2)
    try:
        b = _configured({'port': device.port, 'reconnect_max_ms': 2000.0}, lambda: now[0])
        b.activate()
        device.emulator.kill()
        deadline = time.monotonic() + WAIT
        while not b.read(0.001).status & FAULT:
            assert time.monotonic() < deadline, 'the loss never seen'
            b.write(np.zeros(2))
        for _ in range(10_000):
            now[0] += 1_000_000
            b.write(np.zeros(2))
            assert b.read(0.001).status & FAULT
        redial = b._redial
        assert redial is not None and redial.attempts == 9, redial and redial.attempts
        assert b.fault_reason().endswith('; reconnecting (9 attempts, the newest: cannot '
                                         f'connect to ws://127.0.0.1:{device.port}/: '
                                         'Connection refused)')
        b.deactivate()
        assert b.counters()['reconnect_attempts'] == 9 and b.link() == 'closed'
    finally:
        device.close()


def test_an_attempt_that_never_answers_never_holds_the_cycle(tmp_path: Path) -> None:
    """The service's port taken by a socket that completes TCP connections and never answers
    the handshake, ``connect_timeout_ms`` 10 min: every cycle still returns (FAULT,
    reconnecting), with one attempt under way; a blocking connect would hold the first."""
    device = EmulatorDevice(tmp_path / 'e0', 2)
    silent = socket.socket()
    try:
        b = _configured({'port': device.port, 'connect_timeout_ms': 600_000.0},
                        time.monotonic_ns)
        b.activate()
        device.emulator.kill()
        silent.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        silent.bind(('127.0.0.1', device.port))
        silent.listen(8)
        deadline = time.monotonic() + WAIT
        while not (b._redial is not None and b._redial.attempts == 1):
            assert time.monotonic() < deadline, 'no attempt started'
            b.write(np.zeros(2))
            assert b.read(0.001).status & FAULT
        for _ in range(300):
            b.write(np.zeros(2))
            assert b.read(0.001).status & FAULT
            time.sleep(0.001)
        assert b._redial is not None and b._redial.attempts == 1
        assert b.link() == 'down, reconnecting'
        b.deactivate()
    finally:
        silent.close()
        device.close()


def test_reconnect_max_ms_0_does_not_reconnect(tmp_path: Path) -> None:
    run = Run(tmp_path, (), grasp_ramp_ms=0.0, reconnect_max_ms=0)
    run.until(lambda: run.labels[-1:] == ['grasp'], 'grasping')
    run.device.emulator.kill()
    second = run.device.restart(tmp_path / 'e1')
    run.until(lambda: len(run.labels) > 400 and run.labels[-1] == 'lost', 'lost')
    assert run.backend.link() == 'down' and run.backend.reconnects == 0
    assert re.fullmatch(r'haply: the connection to ws://127\.0\.0\.1:\d+/ ended \([^()]*\)',
                        run.reasons[-1]), run.reasons[-1]
    run.bench.backend.deactivate()
    run.device.stopped = True
    out = second.stop()
    run.device.close()
    assert '"sessions": 0' in out, out
