"""When the loop process applies the LMI updates its node writes to the ring
(``loop_child.UpdateTiming``, ``_RingCycle`` and ``_Child.gap``): in the gap between two
cycles while an update fits before the next deadline, never on the deadline path (wall
clock); before every step in lock-step. Real rings, a real eventfd and the scenario's device
and controller loops; a clock of the test's where the time an apply takes matters."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from types import SimpleNamespace

import pytest

from haptic_topology.control.update_record import encode_update
from haptic_topology.device.loop_child import APPLY_BEFORE, UpdateTiming, _Child, _RingCycle
from haptic_topology.device.pacing import DeadlinePacer
from haptic_topology.device.records import bytes_dtype, put_bytes, update_bytes
from haptic_topology.device.shm_ring import ShmRing
from haptic_topology.sim.lockstep import (
    build_controller_loop,
    build_device_loop,
    virtual_environment,
)
from haptic_topology.sim.scenario import load_scenario

APPLIED = ('applied',)


class _Clock:
    """Time that moves by ``tick`` s each time it is read (an apply reads it twice)."""

    def __init__(self, tick: float) -> None:
        self.t, self.tick = 0.0, tick

    def __call__(self) -> float:
        self.t += self.tick
        return self.t


@pytest.fixture
def parts() -> Iterator[SimpleNamespace]:
    sc = load_scenario('circle')
    ring = ShmRing.create(bytes_dtype(update_bytes(sc.linkage.dof)), 8)
    fd = os.eventfd(0, os.EFD_NONBLOCK)
    ve = virtual_environment(sc)

    def build(lockstep: bool, clock: object = time.monotonic) -> _RingCycle:
        return _RingCycle(build_device_loop(sc), build_controller_loop(sc, sc.mode), ring,
                          UpdateTiming(lockstep), fd, lambda: None, clock)  # type: ignore[arg-type]

    def offer(cycle: _RingCycle, seq: int) -> None:
        """What the node does with an update: prepare, encode, write, signal."""
        put_bytes(ring, encode_update(cycle.controller.ctrl.prepare(ve.snapshot(seq=seq))),
                  'update')
        os.eventfd_write(fd, 1)

    try:
        yield SimpleNamespace(build=build, offer=offer, ring=ring, fd=fd, dt=sc.dt)
    finally:
        os.close(fd)
        ring.close()


def _step(cycle: _RingCycle, k: int, dt: float) -> tuple[str, ...]:
    return cycle.step(k * dt, dt, k * dt).updates


def test_wall_clock_a_step_never_takes_an_update(parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=False)
    parts.offer(cycle, 0)
    assert _step(cycle, 0, parts.dt) == ()            # left in the ring for the next gap
    assert cycle.waiting and not cycle.controller.ctrl.lmi.synced
    cycle.apply_in_gap(time.monotonic() + 10.0, first=True)   # the gap after that step
    assert not cycle.waiting and cycle.controller.ctrl.lmi.synced
    assert _step(cycle, 1, parts.dt) == APPLIED       # reported with the next step


def test_wall_clock_an_update_too_close_to_the_deadline_waits_for_the_next_gap(
        parts: SimpleNamespace) -> None:
    """Less than an update's cost left: it is not applied in this gap, nor by the step that
    follows (the device write would wait for it), but in the gap after that step."""
    cycle = parts.build(lockstep=False)
    parts.offer(cycle, 0)
    cycle.apply_in_gap(time.monotonic() + 0.5 * APPLY_BEFORE, first=False)
    assert cycle.waiting
    cycle.timing.end_gap(cycle.waiting)
    assert _step(cycle, 0, parts.dt) == ()
    assert cycle.waiting and not cycle.controller.ctrl.lmi.synced
    cycle.apply_in_gap(time.monotonic() + 10.0, first=True)
    assert _step(cycle, 1, parts.dt) == APPLIED and not cycle.waiting


def test_wall_clock_each_update_is_checked_against_the_time_left(
        parts: SimpleNamespace) -> None:
    """Two updates waiting, each apply taking 1 ms (the test's clock), 5 ms to the deadline:
    after the first the estimated cost is 1 ms and 1 ms is left: the second waits."""
    clock = _Clock(1e-3)
    cycle = parts.build(lockstep=False, clock=clock)
    parts.offer(cycle, 0)
    parts.offer(cycle, 1)
    cycle.apply_in_gap(5e-3, first=True)
    assert cycle.timing.cost == pytest.approx(1e-3)
    assert cycle.updates_applied == 1 and cycle.waiting
    assert _step(cycle, 0, parts.dt) == APPLIED       # the first one only


def test_wall_clock_an_update_costlier_than_any_gap_is_applied_first_in_the_next_gap(
        parts: SimpleNamespace) -> None:
    """An update that never fits (each apply 2 ms, gaps of 1 ms) waits at most one gap: the
    oldest owed update goes first in the next gap's first look, whatever it costs."""
    clock = _Clock(2e-3)
    cycle = parts.build(lockstep=False, clock=clock)
    cycle.timing.applied(2e-3)                        # measured before: 2 ms each
    parts.offer(cycle, 0)
    cycle.apply_in_gap(clock.t + 1e-3, first=True)    # nothing owed yet: it waits
    assert cycle.waiting
    cycle.timing.end_gap(cycle.waiting)
    cycle.apply_in_gap(clock.t + 1e-3, first=False)   # not the gap's first look
    assert cycle.waiting
    cycle.apply_in_gap(clock.t + 1e-3, first=True)    # the next gap: owed, applied
    assert not cycle.waiting and cycle.updates_applied == 1


def test_lockstep_every_step_takes_the_ring_first(parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=True)
    parts.offer(cycle, 0)
    assert _step(cycle, 0, parts.dt) == APPLIED
    assert not cycle.waiting


def _child(cycle: _RingCycle, fd: int, deadline_in: float) -> SimpleNamespace:
    """What ``_Child.gap`` uses of the child: its ring cycle, a pacer whose next deadline is
    ``deadline_in`` s away, its requests and its wake-up eventfd."""
    pacer = DeadlinePacer(1.0)
    pacer.start(time.monotonic() + deadline_in)
    return SimpleNamespace(cycle=cycle, runner=SimpleNamespace(pacer=pacer),
                           poll_control=lambda: None, stop=False,
                           spec=SimpleNamespace(wake_child=fd))


def test_the_gap_applies_an_update_that_comes_and_lasts_until_the_deadline(
        parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=False)
    parts.offer(cycle, 0)
    started = time.monotonic()
    _Child.gap(_child(cycle, parts.fd, 0.05))
    assert time.monotonic() - started >= 0.049        # select's timeout, never shorter
    assert cycle.controller.ctrl.lmi.synced and not cycle.waiting
    assert _step(cycle, 0, parts.dt) == APPLIED


def test_the_gap_leaves_an_update_that_does_not_fit(parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=False)
    parts.offer(cycle, 0)
    _Child.gap(_child(cycle, parts.fd, 0.5 * APPLY_BEFORE))
    assert cycle.waiting and not cycle.controller.ctrl.lmi.synced
    assert _step(cycle, 0, parts.dt) == ()            # the step does not take it either


def test_a_stop_request_ends_the_gap(parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=False)
    child = _child(cycle, parts.fd, 30.0)

    def stop() -> None:
        child.stop = True

    child.poll_control = stop
    started = time.monotonic()
    _Child.gap(child)
    assert time.monotonic() - started < 30.0
