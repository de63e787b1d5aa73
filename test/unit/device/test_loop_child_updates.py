"""When the loop process applies the LMI updates its node writes to the ring
(``loop_child._RingCycle`` and ``_Child.sleep``): between two cycles while enough time is
left before the next deadline, else after the next cycle (wall clock); before every step in
lock-step. Real rings, a real eventfd and the scenario's device and controller loops."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from types import SimpleNamespace

import pytest

from haptic_topology.control.update_record import encode_update
from haptic_topology.device.loop_child import APPLY_BEFORE, _Child, _RingCycle
from haptic_topology.device.records import bytes_dtype, put_bytes, update_bytes
from haptic_topology.device.shm_ring import ShmRing
from haptic_topology.sim.lockstep import (
    build_controller_loop,
    build_device_loop,
    virtual_environment,
)
from haptic_topology.sim.scenario import load_scenario

APPLIED = ('applied',)


@pytest.fixture
def parts() -> Iterator[SimpleNamespace]:
    sc = load_scenario('circle')
    ring = ShmRing.create(bytes_dtype(update_bytes(sc.linkage.dof)), 8)
    fd = os.eventfd(0, os.EFD_NONBLOCK)
    ve = virtual_environment(sc)

    def build(lockstep: bool) -> _RingCycle:
        return _RingCycle(build_device_loop(sc), build_controller_loop(sc, sc.mode), ring, fd,
                          lambda: None, lockstep)

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


def test_wall_clock_a_step_does_not_take_an_update_that_came_after_the_gap(
        parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=False)
    parts.offer(cycle, 0)
    assert _step(cycle, 0, parts.dt) == ()            # left in the ring for the next gap
    assert cycle.waiting and not cycle.controller.ctrl.lmi.synced
    cycle.apply_early()                               # the gap after that step
    assert not cycle.waiting and cycle.controller.ctrl.lmi.synced
    assert _step(cycle, 1, parts.dt) == APPLIED       # reported with the next step


def test_wall_clock_a_deferred_update_is_taken_by_a_step_that_came_without_a_gap(
        parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=False)
    parts.offer(cycle, 0)
    cycle.defer()                                     # too close to the deadline
    assert _step(cycle, 0, parts.dt) == APPLIED       # the loop overran: no gap came
    assert not cycle.waiting


def test_lockstep_every_step_takes_the_ring_first(parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=True)
    parts.offer(cycle, 0)
    assert _step(cycle, 0, parts.dt) == APPLIED
    assert not cycle.waiting


def _sleeper(cycle: _RingCycle, fd: int) -> SimpleNamespace:
    """What ``_Child.sleep`` uses of the child: its ring cycle and its wake-up eventfd."""
    return SimpleNamespace(cycle=cycle, spec=SimpleNamespace(wake_child=fd))


def test_an_update_is_applied_in_the_gap_when_time_is_left(parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=False)
    parts.offer(cycle, 0)
    started = time.monotonic()
    _Child.sleep(_sleeper(cycle, parts.fd), 30.0)     # returns once it is applied
    assert time.monotonic() - started < 30.0
    assert cycle.controller.ctrl.lmi.synced and not cycle.waiting
    assert _step(cycle, 0, parts.dt) == APPLIED


def test_an_update_too_close_to_the_deadline_waits_and_the_sleep_lasts(
        parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=False)
    parts.offer(cycle, 0)
    started = time.monotonic()
    _Child.sleep(_sleeper(cycle, parts.fd), 0.5 * APPLY_BEFORE)
    assert time.monotonic() - started >= 0.5 * APPLY_BEFORE
    assert cycle.waiting and not cycle.controller.ctrl.lmi.synced
    assert _step(cycle, 0, parts.dt) == APPLIED       # no gap since: the step takes it


def test_a_sleep_without_an_update_lasts_its_time(parts: SimpleNamespace) -> None:
    cycle = parts.build(lockstep=False)
    started = time.monotonic()
    _Child.sleep(_sleeper(cycle, parts.fd), 0.02)
    assert time.monotonic() - started >= 0.019       # select's timeout, never shorter
    assert _step(cycle, 0, parts.dt) == ()
