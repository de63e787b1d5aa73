"""The node side of the hosted layout: the loop's owner, and what publishes its cycles.

:class:`HostedLoop` is what a hosted ``device_driver`` runs instead of executor timers: the
loop process (:class:`~haptic_topology.device.loop_process.LoopProcess`) or, for a backend
that needs rclpy itself, a loop thread (:class:`~haptic_topology.device.runner.LoopRunner`)
stepping the driver's :class:`~haptic_topology.device.loop.DeviceLoop` with the hosted
``lmi_controller``'s :class:`~haptic_topology.control.loop.ControllerLoop`; an
:class:`~haptic_topology.nodes.outbox.OutboxThread` that publishes the cycles' states (the
driver's publisher) and answers (the controller's) from their records, packed to CDR
without decoding them (:class:`~haptic_topology.nodes.wire.CycleWire`); and
:meth:`HostedLoop.check`, called by an executor timer: engagement permission, the loop's
failures, the run's end.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from haptic_topology.control.loop import ControllerLoop
from haptic_topology.device.hosted import HostedCycle
from haptic_topology.device.loop_process import STATUS_PERIOD, LoopProcess
from haptic_topology.device.loop_rings import SortedFigures
from haptic_topology.device.realtime import (
    loop_cpus,
    name_os_thread,
    set_process_affinity,
    set_process_policy,
    set_thread_realtime,
)
from haptic_topology.device.records import CycleCodec
from haptic_topology.device.runner import LoopHandle, LoopRunner, RunnerConfig
from haptic_topology.errors import DeviceError
from haptic_topology.nodes.convert import CONTROLLER_ID
from haptic_topology.nodes.diagnostics import log_notices, monotonic
from haptic_topology.nodes.outbox import OutboxThread, until_batch
from haptic_topology.nodes.separate import SeparateLoop
from haptic_topology.nodes.wire import CycleWire

#: GIL switch interval (s) of a process that hosts the loop thread (CPython's default: 5 ms).
SWITCH_INTERVAL = 2e-4
#: Wall clock: the outbox thread publishes what the loop produced at least this often (s),
#: and, while hand inputs flow, just after each cycle that completes a batch of them
#: (:func:`~haptic_topology.nodes.outbox.until_batch`) ...
PUBLISH_PERIOD = 0.01
#: ... this long (s) after that cycle's deadline (its record is written some 0.1 ms later).
BATCH_MARGIN = 5e-4
#: Lock-step with a loop process: the publishing thread, woken by the child's eventfd after
#: each cycle, also looks this often (s) without a wake-up (a stop, the end of the run).
PROCESS_IDLE_WAKE = 0.05


class HostedLoop:
    """The hosted layout's loop, owned by the ``device_driver`` node ``driver`` (configured:
    its ``loop`` exists) and run with the hosted ``lmi_controller`` node ``controller``.

    Threads: :meth:`start`, :meth:`check`, :meth:`stop`, :meth:`close` and :meth:`values`
    belong to the executor; the loop thread only steps the cycle; the outbox thread
    publishes with ``driver.publish_state`` and ``controller.send``.
    """

    def __init__(self, driver: Any, controller: Any) -> None:
        c = driver.cfg
        if controller.cfg.scenario.name != c.scenario.name:
            raise DeviceError(f'device_driver: hosted lmi_controller runs scenario '
                              f'{controller.cfg.scenario.name}, the device '
                              f'{c.scenario.name}: give both the same scenario')
        self.driver, self.controller = driver, controller
        pacing = RunnerConfig(c.period, driver.lockstep, c.run_duration,
                              controller.cfg.lockstep_wait)
        self.process: LoopProcess | None = None
        self.thread: LoopRunner | None = None
        self.runner: LoopHandle
        drain: Callable[[], np.ndarray]
        if driver.in_child:         # decided once, when the driver configured
            self.runner = self.process = LoopProcess(loop_spec(driver, controller.loop, pacing),
                                                     c.task_dim, controller.dof)
            codec = self.process.codec
            drain = self.process.drain_records
        else:
            thread = LoopRunner(HostedCycle(driver.loop, controller.loop), pacing,
                                wall_ns=lambda: driver.get_clock().now().nanoseconds)
            self.runner = self.thread = thread
            codec = CycleCodec(c.task_dim)
            drain = lambda: codec.records(thread.drain())     # noqa: E731
        self.wire = CycleWire(codec, driver.states.writer, controller.command_wire)
        self._hand_at = codec.position('hand_seq')
        self._update_at = codec.position('update_seq')
        # Lock-step: woken by every cycle (the VE waits on the hand inputs); wall clock: the
        # outbox is drained after each batch of hand inputs, so the loop pays no wake-up.
        self._newest = (0, 0)       # (stamp_ns, hand seq) of the newest record published
        self.outbox = OutboxThread(
            self.runner, drain, self._observe, controller.flush_hand,
            min(controller.flush_period, PUBLISH_PERIOD if not driver.lockstep else
                PROCESS_IDLE_WAKE if self.process is not None else 1.0),
            self.process.wait if self.process is not None else None,
            c.settings.publisher_nice if self.process is not None else 0,
            None if driver.lockstep else self._until_batch)
        if driver.lockstep and isinstance(self.runner, LoopRunner):
            self.runner.wake = self.outbox.wake
        controller.attach(self.runner)
        # The loop thread's percentiles (a minute of periods, the round trips), sorted off the
        # executor thread, as the loop process's are (loop_process.SortedFigures).
        self._figures = SortedFigures(self._sorted, STATUS_PERIOD)
        #: An ended loop thread's figures, and its counts (cycles, round trips) they are of.
        self._final: tuple[tuple[int, int], dict[str, str]] | None = None
        self._problems: list[str] = []      # real-time settings refused (loop thread)
        self._timer: Any = None

    def start(self) -> None:
        """Start the outbox thread (if not running) and the loop thread, with the driver's
        real-time settings, and the executor timer of :meth:`check`. With the loop process,
        return once it has opened the device; raise
        :class:`~haptic_topology.errors.DeviceError` with the backend's reason when it could
        not (:meth:`~haptic_topology.device.loop_process.LoopProcess.wait_started`; the child
        has zeroed and released the device and ended)."""
        s = self.driver.cfg.settings
        # A loop thread must get the GIL back within a fraction of its period when it wakes;
        # CPython lets a thread keep it for up to the switch interval (5 ms). With the loop
        # in its own process no thread here has a deadline: the default spares this
        # process's threads the GIL hand-overs.
        if self.process is None:
            sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL))
        self.runner.may_engage = self.driver.may_engage()
        if self.process is not None:        # a new child: the controller loop starts over
            self.controller.admission.forget()
            # This node's threads, off the deadline path, never preempt the loop process
            # (and with node_cpu_affinity stay off its core).
            self._problems.extend(filter(None, [set_process_policy(s.sched_policy),
                                                set_process_affinity(s.node_cpu_affinity)]))
        self.outbox.start()

        def on_start() -> None:     # in the loop thread
            name_os_thread('device_loop')
            self._problems.extend(set_thread_realtime(s.sched_priority, s.cpu_affinity,
                                                      s.lock_memory, s.sched_slice_us,
                                                      s.timer_slack_ns))

        self.runner.start(on_start=on_start)
        if self.process is not None:
            try:    # the child opens the device: its failure is the activation's
                self.process.wait_started()
            except DeviceError:
                self.runner.stop()
                raise
        self._timer = self.driver.create_timer(0.02, self.check)

    def where(self) -> str:
        """Where the loop runs, for the node's log: ``loop process <pid>`` or ``loop thread``,
        with the CPUs it and (with the loop process) this node's threads are pinned to."""
        s, child = self.driver.cfg.settings, self.process
        pins = [('', s.cpu_affinity)] + ([(', this node', s.node_cpu_affinity)]
                                         if child is not None else [])
        return ((f'loop process {child.pid}' if child is not None else 'loop thread')
                + ''.join(f'{who} on CPUs {list(cpus)}' for who, cpus in pins if cpus != (-1,)))

    def check(self) -> None:
        """Executor timer: engagement permission; the loop thread's (or the outbox's)
        failure is the driver's fault; at the end of the run (``run_duration`` reached and
        every state of it published: tools take the driver's "inactive" as the end) the
        driver deactivates."""
        runner, d = self.runner, self.driver
        if self.process is not None:
            self.process.check()
        runner.may_engage = d.may_engage()
        if self.outbox.problem:
            self._problems.append(self.outbox.problem)
            self.outbox.problem = None
        while self._problems:
            d.get_logger().warn(self._problems.pop(0))
        error = runner.error or self.outbox.error
        if error is not None:
            d.fail(f'loop thread failed: {type(error).__name__}: {error}')
            d.trigger_deactivate()
        elif runner.finished and self.outbox.caught_up():
            d.end_run()

    def stop(self) -> None:
        """Stop the loop thread; the outbox thread goes on (until :meth:`close`): it
        publishes what the loop left and flushes the controller's last hand-input batch."""
        if self._timer is not None:
            self.driver.destroy_timer(self._timer)
            self._timer = None
        self.runner.stop()

    def close(self) -> None:
        self.outbox.stop()
        self._figures.stop()
        if self.process is not None:
            self.process.close()

    @property
    def running(self) -> bool:
        """Whether states may still be published (the bringup's end-of-run check)."""
        return self.runner.running or not self.outbox.caught_up()

    def values(self) -> dict[str, str]:
        """The loop's figures as the device's (:meth:`LoopRunner.device_values`), with the
        loop thread's round-trip percentiles (the device loop reports them as NaN here:
        ``device_driver`` asks it without). While the loop thread runs, every percentile is
        the newest the figures' thread has, never sorted on the caller's thread."""
        # The hosted controller's commands are published with this process's id.
        if self.thread is None:
            return {**self.runner.device_values(), 'controller_id': str(CONTROLLER_ID)}
        running = self.thread.running
        out = self.thread.device_values(percentiles=not running)
        if running:
            out.update(self._figures.read())
        else:       # an ended loop's: sorted once, not again at every diagnostics tick
            ended = (self.thread.pacer.cycles, self.thread.cycle.device.round_trips[1])
            if self._final is None or self._final[0] != ended:
                self._final = (ended, self._sorted())
            out.update(self._final[1])
        return {**out, 'controller_id': str(CONTROLLER_ID)}

    def _sorted(self) -> dict[str, str]:
        """The figures' thread: the loop thread's period, wake-up lateness and round-trip
        percentiles."""
        assert self.thread is not None
        pacing = self.thread.pacer.figures()
        rtt = self.thread.cycle.device.figures()
        return {**pacing.values(), **pacing.values('loop_'),
                **{f'round_trip_{q}_ms': f'{rtt[f"round_trip_{q}_ms"]:.3f}'
                   for q in ('p50', 'p99')}}

    def _until_batch(self) -> float:
        """Outbox thread, wall clock: how long to wait for the next batch of hand inputs."""
        stamp, hand = self._newest
        return until_batch(time.time_ns(), stamp, hand, self.controller.port.batcher.period,
                           self.driver.cfg.period_ns, round(BATCH_MARGIN * 1e9),
                           PUBLISH_PERIOD)

    def _observe(self, recs: np.ndarray) -> None:
        """Outbox thread: the cycles' states (and ``/clock``), then the controller's
        commands and hand inputs, from the records ``recs``."""
        d, c, wire = self.driver, self.controller, self.wire
        srcs = [i + f + wire.extras(i[0])
                for i, f in zip(recs['i'].tolist(), recs['f'].tolist(), strict=True)]
        self._newest = (srcs[-1][0], srcs[-1][self._hand_at])
        for src in srcs:
            d.publish_state(wire.state(src), src[0], clock=d.lockstep)
        now = monotonic()
        # Wall clock: a state's stamp (ns) on this clock, for the age of the update its
        # answer used at the state's time (lock-step: published as soon as it ran).
        to_now = now - 1e-9 * time.time_ns()
        floats = recs['f']
        for n, src in enumerate(srcs):
            if not wire.answered(src):
                continue
            ns = src[0]
            used = None if d.lockstep else (src[self._update_at], min(now, 1e-9 * ns + to_now))
            age, batch = c.port.answered_block(wire.hand(src, floats[n]), ns, now,
                                               None if wire.idle(src) else 1e-9 * ns, used)
            c.cmd_pub.publish(wire.command(src, age))
            if batch is not None:
                c.publish_hand(batch)
        log_notices(c, c.loop.notices)
        log_notices(d, self.runner.notices)


def in_child(driver: Any) -> bool:
    """Whether the configured hosted ``driver`` runs its loop in a loop process: with
    ``loop_process``, unless its backend uses rclpy itself."""
    return bool(driver.cfg.settings.loop_process) and not driver.backend.needs_ros


def loop_spec(driver: Any, controller: ControllerLoop, pacing: RunnerConfig) -> dict[str, Any]:
    """What the loop process of ``driver`` builds its loop from (see
    :class:`~haptic_topology.device.loop_process.LoopSpec`)."""
    c, s = driver.cfg, driver.cfg.settings
    return dict(backend=c.backend, backend_config=c.backend_config(),
                limit=np.asarray(c.wrench_limit, dtype=float), watchdog=c.watchdog,
                period=c.period, takeover_after=c.takeover_after, controller=controller,
                runner=pacing, sched_priority=s.sched_priority,
                cpu_affinity=loop_cpus(s.cpu_affinity, s.node_cpu_affinity),
                lock_memory=s.lock_memory,
                sched_slice_us=s.sched_slice_us, timer_slack_ns=s.timer_slack_ns)


def driver_layout(driver: Any, hosted: Any) -> HostedLoop | SeparateLoop:
    """The configured ``driver``'s layout: :class:`HostedLoop` around the ``lmi_controller``
    node ``hosted`` with ``host_controller``, else :class:`SeparateLoop`."""
    if not driver.cfg.settings.host_controller:
        return SeparateLoop(driver)
    if hosted is None:
        raise DeviceError('host_controller is true but no lmi_controller is hosted (start the '
                          'node with its main, or set host_controller false and run '
                          'lmi_controller)')
    return HostedLoop(driver, hosted)
