"""A node process's life: executor, spin until SIGINT/SIGTERM, clean shutdown and exit.

Executors: :class:`rclpy.experimental.EventsExecutor` by default (about 6 us per callback
against 130 us for the ``SingleThreadedExecutor``), spun with ``spin_once(timeout_sec=0.1)``
in a loop: in this rclpy build ``spin()`` and ``spin_once()`` without a timeout burn a core
and ignore SIGINT. ``executor: single_threaded`` is the fallback. The
``MultiThreadedExecutor`` is not offered (it collapses at 1 kHz in rclpy 7.1).
"""

from __future__ import annotations

import faulthandler
import gc
import os
import signal
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from haptic_topology.config.params import NodeParams
from haptic_topology.device.realtime import (
    NODE_POLICIES,
    fix_mmap_threshold,
    renice_process,
    reset_session_nice,
    set_process_affinity,
    set_process_policy,
    set_realtime_priority,
)
from haptic_topology.errors import ConfigError, HapticTopologyError
from haptic_topology.nodes.dds_env import localhost_discovery_default
from haptic_topology.nodes.parameters import check_config_args
from haptic_topology.processes import stacks_on_signal
from haptic_topology.sampling import dump_now, start_from_env


def make_executor(kind: str) -> Any:
    if kind == 'events':
        from rclpy.experimental import EventsExecutor
        return EventsExecutor()
    return SingleThreadedExecutor()


#: Seconds after SIGINT/SIGTERM at which a node still running dumps its threads' stacks (the
#: bringup escalates to SIGTERM after 5 s).
STOP_DUMP_AFTER = 4.0
#: s: the longest wait of :func:`spin`'s loop (it sees a stop signal within this)
SPIN_PERIOD = 0.1
#: s :func:`spin` gives the executor to shut down after the loop
EXECUTOR_SHUTDOWN = 1.0


def freeze_startup_objects() -> None:
    """Collect once, then move every object the process holds so far (the imported modules,
    the nodes, their models: about 136,000 in ``ve_sim``) out of the collector's reach
    (:func:`gc.freeze`). They live as long as the process; a full collection would otherwise
    walk them all, which stops the node for about 60 ms (``ve_sim``, ``device_driver``:
    ``bench/gc_pause.py``), longer than the LMI updates may be late (``stale_after``).
    Afterwards a collection walks only objects made since; the node's memory is
    unchanged. :func:`spin` calls it before it spins."""
    gc.collect()
    gc.freeze()


def spin(nodes: Sequence[Node], kind: str) -> None:
    """Spin ``nodes`` on one executor until SIGINT/SIGTERM (or rclpy's shutdown).

    The stop signals are this function's own (Python handlers installed after the executor
    exists, the previous ones restored when it returns): rclpy's ``EventsExecutor`` installs
    an asio handler for SIGINT and SIGTERM when it is created, and measured here a recorder
    idling on it ignored the SIGINT in 2 of 13 tries (it went on spinning normally, main
    thread in ``spin_once``'s timed wait, until SIGKILL): the bringup's "node did not exit"
    failures. A Python handler only sets a flag; ``spin_once`` returns every 0.1 s, so the
    loop ends within that after the signal, whatever the executor does with signals. The
    handlers stay for the rest of the process (see below).
    """
    executor = make_executor(kind)
    for n in nodes:
        executor.add_node(n)
    freeze_startup_objects()
    stop: list[int] = []

    def request_stop(signum: int, frame: Any) -> None:
        if not stop:
            # A node that has not ended STOP_DUMP_AFTER s after the signal writes every
            # thread's Python stack to stderr (its log): where a stop hangs, not a guess.
            faulthandler.dump_traceback_later(STOP_DUMP_AFTER, exit=False)
            reset_session_nice()        # the teardown does not wait behind busy sessions
        stop.append(signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        # Kept after the loop: a second signal must not raise KeyboardInterrupt in the
        # middle of the nodes' close (the recorder finalising its bag); a teardown that
        # hangs gets the bringup's SIGKILL.
        signal.signal(sig, request_stop)
    try:
        while rclpy.ok() and not stop:
            executor.spin_once(timeout_sec=SPIN_PERIOD)
    finally:
        executor.shutdown(timeout_sec=EXECUTOR_SHUTDOWN)


def run_main(prog: str, build: Callable[[], Sequence[Node]],
             args: Sequence[str] | None = None,
             params: Mapping[str, NodeParams | None] | None = None,
             exit_after_close: bool = False) -> int:
    """Init rclpy, build the node(s), spin, shut down cleanly; return the exit status.

    ``exit_after_close``: end the process with the status once the nodes' ``close`` has run,
    without rclpy's teardown (the recorder, see the comment at the end). Called as a
    program (``args`` None) the process always ends in this function, after rclpy's
    shutdown and without the interpreter's finalization (see the end).

    ``params``: node name -> its declared parameters (None: unknown here), used to check the
    params files and ``-p`` overrides before rclpy reads them; ``prog`` is the node checked
    (all of ``params`` for ``composed``). DDS discovery defaults to this host
    (:func:`localhost_discovery_default`).

    A configuration problem (params file, parameter, scenario) prints one line
    ``<prog>: error: ...`` and returns 2 without a traceback.
    """
    argv = list(sys.argv if args is None else args)
    localhost_discovery_default(os.environ)
    stacks_on_signal()
    start_from_env()
    fix_mmap_threshold()        # before rclpy.init and the nodes: RSS stays flat over hours
    if params is not None:
        try:
            check_config_args(argv, params, prog if prog in params else None)
        except ConfigError as exc:
            print(f'{prog}: error: {exc}', file=sys.stderr)
            return 2
    try:
        rclpy.init(args=argv)
    except (RuntimeError, ValueError) as exc:  # rclpy's RCLError is a RuntimeError
        print(f'{prog}: error: invalid ROS arguments or params file: {_first_line(exc)}',
              file=sys.stderr)
        return 2
    nodes: list[Node] = []
    status = 0
    try:
        nodes = list(build())
        kind = str(nodes[0].get_parameter('executor').value) if nodes else 'events'
        # A node that applies real-time settings to its own loop thread (the hosted
        # device_driver) sets ``process_sched_priority`` = 0: the rest of its process stays
        # under normal scheduling.
        priority = max((int(getattr(n, 'process_sched_priority',
                                    n.get_parameter('sched_priority').value))
                        for n in nodes if n.has_parameter('sched_priority')), default=0)
        if priority:
            problem = set_realtime_priority(priority)
            if problem:
                nodes[0].get_logger().warn(problem)
            else:
                nodes[0].get_logger().info(f'SCHED_FIFO priority {priority}')
        # Nodes off the deadline path yield the CPU (``nice``); a process that also holds a
        # node without the parameter (the composed graph, with the loop) stays as it is.
        # They also run under SCHED_BATCH or SCHED_IDLE (``sched_policy``), unless under
        # SCHED_FIFO; of several nodes in one process, the one that yields least decides.
        if nodes and all(n.has_parameter('nice') for n in nodes):
            nice = min(int(n.get_parameter('nice').value) for n in nodes)
            policy = 'other' if priority else min(
                (str(n.get_parameter('sched_policy').value) if n.has_parameter('sched_policy')
                 else 'other' for n in nodes), key=list(NODE_POLICIES).index)
            # Pinned only when every node asks for it (the union of their CPUs).
            pins = [tuple(n.get_parameter('cpu_affinity').value)
                    if n.has_parameter('cpu_affinity') else (-1,) for n in nodes]
            cpus = [-1] if (-1,) in pins else sorted(set().union(*pins))
            problems = [renice_process(nice) if nice else None, set_process_policy(policy),
                        set_process_affinity(cpus)]
            for text in filter(None, problems):
                nodes[0].get_logger().warn(text)
            applied = policy != 'other' and problems[1] is None
            pinned = cpus != [-1] and problems[2] is None
            nodes[0].get_logger().info(f'nice +{nice}'
                                       + (f', SCHED_{policy.upper()}' if applied else '')
                                       + (f', CPUs {cpus}' if pinned else ''))
        spin(nodes, kind)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except HapticTopologyError as exc:
        print(f'{prog}: error: {exc}', file=sys.stderr)
        status = 2
    except (ParameterException, RuntimeError) as exc:
        if not rclpy.ok():  # shutting down: a late rcl error is not a config problem
            pass
        else:
            print(f'{prog}: error: {_first_line(exc)}', file=sys.stderr)
            status = 2
    finally:
        if not close_all(nodes, prog):
            status = status or 1
        # The nodes go before the process ends on every path: the last one destroyed
        # deletes the process's DDS participant, and with it Fast DDS's shared-memory
        # segment in /dev/shm, which outlives a process that ends with it alive.
        destroy_nodes(nodes)
        if exit_after_close:
            # Everything the nodes own is closed (the recorder's bag is complete): nothing
            # is left for rclpy's teardown to do. (Clean-clone CI runs had reported the
            # recorder "hung" here; the cause found later was the lost SIGINT, see spin().)
            _end_process(status)
        rclpy.try_shutdown()
    if args is None:
        # A node process (console script, python -m) ends here, without the interpreter's
        # finalization: everything ROS is shut down above, and finalization only destroys
        # rclpy's and Fast DDS's C++ objects once more. Measured: under load that took over
        # 4 s after run_main had returned (faulthandler: the main thread with no Python
        # frame), and the bringup's SIGTERM ended the process with -15.
        _end_process(status)
    return status


def destroy_nodes(nodes: Sequence[Node]) -> None:
    """Destroy ``nodes`` and what keeps their rcl node alive besides them: a lifecycle node's
    state machine, which rclpy 7.1's ``LifecycleNode.destroy_node`` leaves in place. While an
    rcl node lives, its context's DDS participant does too (it goes with the context's last
    node), and a process that ends with its participant alive leaves the participant's
    shared-memory segment in ``/dev/shm`` (:mod:`haptic_topology.nodes.dds_shm`)."""
    for n in nodes:
        machine = getattr(n, '_state_machine', None)     # rclpy.lifecycle.LifecycleNode
        if machine is not None:
            machine.destroy_when_not_in_use()
        n.destroy_node()


def close_all(nodes: Sequence[Node], prog: str) -> bool:
    """Call every node's ``close`` (if it has one), in order, whatever the others do: one that
    raises is reported (``<prog>: error: <node>: closing failed: ...`` on stderr) and the next
    ones are closed all the same (the recorder, finalising its bag, among them). Returns
    whether every close succeeded (a process then exits with status 1)."""
    ok = True
    for n in nodes:
        close = getattr(n, 'close', None)
        if close is None:
            continue
        try:
            close()
        except Exception as exc:  # reported; the other nodes are closed all the same
            what = (str(exc) if isinstance(exc, HapticTopologyError)
                    else f'closing failed: {type(exc).__name__}: {exc}')
            print(f'{prog}: error: {n.get_name()}: {what}', file=sys.stderr, flush=True)
            ok = False
    return ok


def _end_process(status: int) -> None:
    """``os._exit(status)`` after the sampling profiler's dump and the stdio buffers (no
    ``atexit`` function runs after it)."""
    dump_now()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
