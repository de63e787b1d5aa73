"""The stop's time budget: a node process's teardown ends before the bringup escalates.

``haptic-topology run`` stops each node with SIGINT, then SIGTERM after ``STOP_TIMEOUT`` s and
SIGKILL ``STOP_ESCALATE`` s later. A node's spin loop sees the signal within ``SPIN_PERIOD``,
the executor gets ``EXECUTOR_SHUTDOWN``, and the recorder waits at most ``CLOSE_TIMEOUT`` for
its writer thread to finish the bag: all of it must fit before the SIGTERM, with room left."""

from __future__ import annotations

import inspect

from haptic_topology.bringup import run
from haptic_topology.nodes import recorder, runtime
from haptic_topology.processes import STOP_ESCALATE, STOP_TIMEOUT, terminate


def test_the_recorders_close_is_bounded_below_the_bringups_stop_timeout() -> None:
    teardown = runtime.SPIN_PERIOD + runtime.EXECUTOR_SHUTDOWN + recorder.CLOSE_TIMEOUT
    assert teardown + 0.5 <= STOP_TIMEOUT < STOP_TIMEOUT + STOP_ESCALATE
    assert recorder.CLOSE_TIMEOUT >= 2.0       # enough to finish a bag's last file


def test_the_bringup_stops_with_the_named_timeouts() -> None:
    assert inspect.signature(run.stop).parameters['timeout'].default == STOP_TIMEOUT
    params = inspect.signature(terminate).parameters
    assert params['timeout'].default == STOP_TIMEOUT
    assert params['escalate'].default == STOP_ESCALATE
