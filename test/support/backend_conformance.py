"""What every device backend must do, checked the same way for each one (no ROS here).

A :class:`Bench` drives one backend, selected by name as ``device_driver`` selects it
(:func:`~haptic_topology.device.backend.create_backend`), through the driver's core loop
(:class:`~haptic_topology.device.loop.DeviceLoop`, the scenario's wrench limit, the default
watchdog: timeout 5 ms, ramp 50 ms) with loop times of its own (1 ms per cycle), and records
what the loop wrote and what reached the device (a :class:`DeviceSide`: the backend's own
account for a device in this process, the device process's record for one behind topics).
The checks, each one test per backend (``test_device_conformance.py``,
``test_topic_backend.py``):

* :func:`check_clamping`: commands up to 3x the limit: every wrench written and every wrench
  the device got is finite and within the limit, the readings are finite;
* :func:`check_nonfinite`: a NaN/inf wrench given to ``write`` never reaches the device;
* :func:`check_watchdog`: commands stop -> the output fades (never grows) to exactly zero and
  the device gets zero before commands return; they return -> it fades back to the command;
* :func:`check_lifecycle`: ``activate`` before ``configure`` is refused; configure ->
  activate -> cycles -> zero and deactivate (twice is harmless: the device's last wrench is
  zero; ``write`` refused) -> activate again -> cycles -> ``cleanup`` and a new instance
  configured and activated (the driver's cleanup and configure) -> cycles -> cleanup (twice:
  harmless).

Assertions are on values only (finite, within limits, exactly zero, exactly the command),
never on timing.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from haptic_topology.device.backend import (
    BackendConfig,
    DeviceBackend,
    create_backend,
    zero_and_release,
)
from haptic_topology.device.loop import DeviceLoop, DeviceTick
from haptic_topology.device.watchdog import CommandWatchdog, WatchdogConfig
from haptic_topology.errors import DeviceError
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import ControlMode

PENALTY = int(ControlMode.PENALTY)
#: Relative tolerance of a wrench that went through a device's units and axes and back.
ROUND_TRIP = 1e-12


class DeviceSide(Protocol):
    """What reached the device behind a backend."""

    def after_cycle(self, backend: DeviceBackend) -> None:
        """Called after every cycle (and after a release) of the bench."""

    def got(self, expected: np.ndarray, after_ns: int) -> bool:
        """Whether the device's newest wrench is ``expected`` (to the round-trip tolerance),
        got at ``after_ns`` (monotonic ns) or later."""

    def poll(self, seconds: float) -> None:
        """Take news from the device for up to ``seconds`` (a device in another process)."""

    def log(self) -> tuple[np.ndarray, np.ndarray]:
        """``(t_ns, wrenches)``: monotonic arrival time (ns) and task wrench (n x m) of
        everything the device got so far (called once, at the end of a check)."""


def same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal to the round-trip tolerance (relative, per entry)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return bool(np.all(np.abs(a - b) <= ROUND_TRIP * (1.0 + np.abs(b))))


class Applied:
    """A device in this process whose backend says what it applies (``backend.applied``:
    the simulated maglev, the example backend)."""

    def __init__(self) -> None:
        self.t: list[int] = []
        self.w: list[np.ndarray] = []

    def after_cycle(self, backend: DeviceBackend) -> None:
        self.t.append(time.monotonic_ns())
        self.w.append(np.array(backend.applied, dtype=float))  # type: ignore[attr-defined]

    def got(self, expected: np.ndarray, after_ns: int) -> bool:
        return bool(self.t) and self.t[-1] >= after_ns and same(self.w[-1], expected)

    def poll(self, seconds: float) -> None:
        pass

    def log(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.t, dtype=np.int64), np.array(self.w)


#: Longest wait (s) for a device in another process to get a wrench.
SETTLE_WAIT = 60.0


@dataclass
class Subject:
    """A backend under test: its name (as the ``backend`` parameter), options, scenario, how
    to see its device, and ``pace`` (called before each cycle: a device on its own clock
    needs the cycles spread out in wall time)."""

    backend: str
    device: Callable[[], DeviceSide]
    options: dict[str, Any] = field(default_factory=dict)
    scenario: str = 'fig8'
    pace: Callable[[], None] = lambda: None


class Bench:
    """One backend in the core loop (module doc)."""

    def __init__(self, subject: Subject, device: DeviceSide | None = None) -> None:
        self.subject = subject
        self.sc = load_scenario(subject.scenario)
        self.m = self.sc.linkage.task.dim
        self.limit = np.asarray(self.sc.device.wrench_limit, dtype=float)
        self.dt = self.sc.dt
        self.config = BackendConfig(self.sc.device, initial_device_pose(self.sc),
                                    dict(self.sc.user), dict(subject.options), self.sc.source)
        self.device = device if device is not None else subject.device()
        self.written: list[np.ndarray] = []
        self.readings: list[np.ndarray] = []
        self.t = 0.0
        self.backend = self.new_backend()
        self.loop = self.new_loop()

    def new_backend(self) -> DeviceBackend:
        backend = create_backend(self.subject.backend)
        backend.configure(self.config)
        assert backend.task_dim() == self.m
        assert backend.hardware_id.startswith(backend.name)
        return backend

    def new_loop(self) -> DeviceLoop:
        return DeviceLoop(self.backend, self.limit, CommandWatchdog(WatchdogConfig(), self.m),
                          self.dt)

    def _record(self, tick: DeviceTick) -> DeviceTick:
        r = tick.reading
        self.readings.append(np.concatenate([r.pose, r.twist, r.hand_wrench]))
        self.device.after_cycle(self.backend)
        return tick

    def activate(self) -> None:
        """``activate``, a new loop, idle cycles (zero wrench) until the device gets them: a
        device in another process may not hear the first commands of a new connection."""
        self.backend.activate()
        self.loop = self.new_loop()
        mark = time.monotonic_ns()
        deadline = time.monotonic() + SETTLE_WAIT
        while True:
            self.tick()
            self.device.poll(0.0)
            if self.device.got(np.zeros(self.m), mark):
                break
            assert time.monotonic() < deadline, 'the device never got a command'

    def settle(self, expected: np.ndarray, after_ns: int) -> None:
        """Return once the device's newest wrench is ``expected``, got at ``after_ns`` or
        later (no cycles meanwhile)."""
        deadline = time.monotonic() + SETTLE_WAIT
        while not self.device.got(expected, after_ns):
            assert time.monotonic() < deadline, f'the device never got {expected.tolist()}'
            self.device.poll(0.02)

    def engage(self) -> None:
        """Idle state, its answer (zero wrench, penalty mode) engages, the resting state."""
        tick = self.tick()
        assert self.loop.on_command(tick.seq, PENALTY, np.zeros(self.m), self.t) == 'applied'
        self.tick()
        assert self.loop.engaged and self.loop.run_index == 0

    def tick(self) -> DeviceTick:
        self.subject.pace()
        self.t += self.dt
        tick = self.loop.tick(self.t, self.dt)
        if self.loop.run_index > 0:
            self.written.append(np.array(tick.applied, dtype=float))
        return self._record(tick)

    def cycle(self, command: np.ndarray | None) -> DeviceTick:
        """One engaged cycle: the newest state answered with ``command`` (None: no answer)."""
        if command is not None:
            assert self.loop.on_command(self.loop.seq, PENALTY, command, self.t) == 'applied'
        return self.tick()

    def release(self) -> None:
        """What the driver does on deactivate: zero wrench, then ``deactivate``; returns once
        the device has got the zero."""
        mark = time.monotonic_ns()
        zero_and_release(self.backend, self.m)
        self.device.after_cycle(self.backend)
        self.settle(np.zeros(self.m), mark)


def _finite_within(w: np.ndarray, limit: np.ndarray, what: str) -> None:
    assert w.size, f'{what}: nothing'
    assert np.all(np.isfinite(w)), f'{what}: not finite'
    over = np.abs(w) > limit * (1.0 + ROUND_TRIP)
    assert not over.any(), f'{what}: beyond the limit {limit}: {w[over.any(axis=1)][:3]}'


def _rows_among(rows: np.ndarray, allowed: np.ndarray, scale: np.ndarray) -> None:
    """Every row of ``rows`` is one of ``allowed`` or less of it (per axis the same sign, no
    larger: a device's own saturation), to the round-trip tolerance: nothing reached the
    device that the loop did not write."""
    tol = ROUND_TRIP * scale
    for r in rows:
        ok = np.all((np.abs(r) <= np.abs(allowed) + tol) & (r * allowed >= -tol * tol), axis=1)
        assert ok.any(), f'device got {r}, never written'


def _zero(a: np.ndarray) -> np.ndarray:
    return np.all(a == 0.0, axis=-1)


def check_clamping(bench: Bench, cycles: int = 600, seed: int = 15) -> None:
    rng = np.random.default_rng(seed)
    bench.activate()
    bench.engage()
    for _ in range(cycles):
        bench.cycle(rng.uniform(-3.0, 3.0, bench.m) * bench.limit)
    # Last, a command beyond the limit on every axis, repeated (a device on its own clock
    # may take only some of the commands of a busy machine, and a best-effort sample may be
    # lost), until the device holds its clamped value: so the device did get clamped
    # commands, whatever the machine's load.
    beyond = 3.0 * bench.limit * np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])[:bench.m]
    mark = time.monotonic_ns()
    for _ in range(20):
        bench.cycle(beyond)
    bench.settle(np.array(bench.written[-1]), mark)
    bench.release()
    written = np.array(bench.written)
    _finite_within(written, bench.limit, 'written')
    assert bench.loop.saturated_cycles > cycles // 2       # the clamp did act
    np.testing.assert_array_equal(np.abs(written[-1]), bench.limit)
    assert np.all(np.isfinite(np.array(bench.readings))), 'a reading is not finite'
    _, dev = bench.device.log()
    _finite_within(dev, bench.limit, 'device')
    _rows_among(dev, np.vstack([written, np.zeros(bench.m)]), bench.limit)
    at_limit = np.isclose(np.abs(dev), bench.limit, rtol=ROUND_TRIP, atol=0.0).all(axis=1)
    assert at_limit.any(), 'the device never got the clamped command'


def check_nonfinite(bench: Bench) -> None:
    """NaN/inf entries given to ``write`` reach the device as 0; the finite ones as given."""
    bench.activate()
    bad = np.array([np.nan, 0.5, np.inf, -np.inf, 0.25, np.nan])[:bench.m]
    clean = np.where(np.isfinite(bad), bad, 0.0)
    mark = time.monotonic_ns()
    for _ in range(20):
        bench.subject.pace()
        bench.backend.write(bad)
        r = bench.backend.read(bench.dt)
        assert all(np.all(np.isfinite(v)) for v in (r.pose, r.twist, r.hand_wrench))
        bench.device.after_cycle(bench.backend)
    bench.settle(clean, mark)
    bench.release()
    _, dev = bench.device.log()
    assert dev.size and np.all(np.isfinite(dev)), 'a non-finite wrench reached the device'
    assert all(same(w, clean) or not w.any() for w in dev), 'the device got something else'


def check_watchdog(bench: Bench, answered: int = 60, silent: int = 150,
                   resumed: int = 120) -> None:
    bench.activate()
    bench.engage()
    u = 0.5 * bench.limit * np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])[:bench.m]
    for _ in range(answered):
        bench.cycle(u)
    k0, w_stop = len(bench.written), time.monotonic_ns()
    for _ in range(silent):
        bench.cycle(None)
    bench.settle(np.zeros(bench.m), w_stop)
    k1, w_resume = len(bench.written), time.monotonic_ns()
    for _ in range(resumed):
        bench.cycle(u)
    # A device on its own clock that got no CPU across the last cycles has not applied the
    # command yet: wait until it has (it applies only the newest command), then release.
    bench.settle(u, w_resume)
    bench.release()
    written = np.array(bench.written)
    np.testing.assert_array_equal(written[k0 - 1], u)
    stopped = np.abs(written[k0:k1])
    assert np.all(np.diff(stopped, axis=0) <= 0.0), 'the output grew without commands'
    zero = np.flatnonzero(_zero(written[k0:k1]))
    assert zero.size, 'the output never reached zero'
    assert np.all(_zero(written[k0 + zero[0]:k1])), 'the output left zero without commands'
    assert bench.loop.watchdog.trips == 1
    back = np.abs(written[k1:])
    assert np.all(np.diff(back, axis=0) >= 0.0), 'the fade-in went down'
    np.testing.assert_array_equal(written[-1], u)            # faded back in fully
    t, dev = bench.device.log()
    _finite_within(dev, bench.limit, 'device')
    window = dev[(t >= w_stop) & (t <= w_resume)]
    assert window.size, 'the device got nothing while commands had stopped'
    first = np.flatnonzero(_zero(window))
    assert first.size, 'the device never got zero while commands had stopped'
    assert np.all(_zero(window[first[0]:])), 'the device got force again without commands'
    assert np.all(np.diff(np.abs(window), axis=0) <= ROUND_TRIP * bench.limit)
    after = dev[t > w_resume]
    assert np.any(np.abs(after - u).max(axis=1) <= ROUND_TRIP * bench.limit.max()), \
        'the device never got the command back'
    assert np.all(_zero(dev[-1])), 'the device was not left at zero'


def check_lifecycle(bench: Bench, cycles: int = 40) -> None:
    fresh = create_backend(bench.subject.backend)
    try:
        fresh.activate()
    except DeviceError:
        pass
    else:
        fresh.deactivate()
        raise AssertionError('activate() before configure() was accepted')
    u = 0.25 * bench.limit
    marks = []
    for round_ in range(3):
        if round_ == 2:             # cleanup + configure: a new instance, as the driver does
            bench.backend.cleanup()
            bench.backend = bench.new_backend()
        bench.activate()
        bench.engage()
        sent = time.monotonic_ns()
        for _ in range(cycles):
            bench.cycle(u)
        np.testing.assert_array_equal(bench.written[-1], u)
        # A device in another process hears the commands later, how much later depends on
        # the machine's load (a CI run under load: not within the 40 cycles).
        bench.settle(u, sent)
        marks.append(time.monotonic_ns())
        bench.release()
        bench.backend.deactivate()              # twice: harmless
        bench.device.after_cycle(bench.backend)
        marks.append(time.monotonic_ns())
    bench.backend.cleanup()
    bench.backend.cleanup()                     # twice: harmless
    t, dev = bench.device.log()
    _finite_within(dev, bench.limit, 'device')
    for k in range(3):
        start = marks[2 * k - 1] if k else 0
        got = dev[(t > start) & (t <= marks[2 * k + 1])]
        assert np.any(np.abs(got - u).max(axis=1) <= ROUND_TRIP * bench.limit.max()), \
            f'activation {k + 1}: the device never got the command'
        assert np.all(_zero(got[-1])), f'activation {k + 1}: not zero after deactivate'


#: The checks by name (a test parametrized over some of them).
CHECKS: dict[str, Callable[[Bench], None]] = {
    'clamping': check_clamping, 'nonfinite': check_nonfinite, 'watchdog': check_watchdog,
    'lifecycle': check_lifecycle}
