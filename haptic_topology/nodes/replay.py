"""``haptic-topology replay BAG``: publish a bag's messages with their recorded timing.

Plain replay publishes every message (or those of ``--topics``) as the recorded CDR bytes
(``Publisher.publish(bytes)``, nothing is deserialised) on its recorded topic, at the
recorded receive times scaled by ``1 / --rate``, from ``--start-offset`` seconds into the
bag, once or ``--loop``. Each topic gets the QoS its publishers offered (the bag's
``offered_qos_profiles``), so e.g. a recorder or a viewer sees them as it saw the run. A
live ``lmi_controller`` takes LMI updates only from a ``ve_sim`` of its graph and refuses
those of a replay while its own VE is gone (``docs/safety.md``); ``--check-controller``
below is the way to feed it a bag. A topic whose type the bag holds in
an older definition than the installed one is re-serialised as the installed type when
fields were only appended since (``LmiUpdate`` and ``DeviceState`` before their contact
fields: the new fields empty or zero, :func:`~haptic_topology.bag.reader.upgraders`), and
left out, and named in the summary line, when the definition changed otherwise
(``DeviceCommand`` before ``controller_id``, a field inserted in the middle): its bytes would
be misread as the current type; naming it in ``--topics`` is an error.

``--check-controller`` is the controller's regression check: it starts ``lmi_controller``
itself (in its own namespace, with the bag's scenario and the recorded control law), feeds
it the recorded device states and LMI updates, records its commands and compares them with
the recorded ones state by state. What the controller needs to reproduce a command exactly:

* the same parameters (scenario, mode; the gains are the scenario's);
* the same states, in order, and only those it answered in the run: a state it skipped
  (late, overwritten in its depth-1 queue) changes the next cycle's ``dt``;
* each LMI update taken between the same two states as in the run. Every command carries
  ``update_seq``, the newest update its controller had taken, so the plan places the
  updates (in the bag's order, the VE's publishing order) up to that one before the state
  (:func:`~haptic_topology.bag.controller_check.controller_plan`). A bag recorded before
  that field existed is planned from ``update_age``, which grows from command to command
  while the controller uses the same update: ``header.stamp - update_age`` is when it
  received its newest one, and before the first state of each such group every update the
  VE had published (its header stamp) by then is applied, at least the next one.

Only commands whose state is in the bag are compared (the recorder may have joined after
the device started). A command naming an update the bag does not hold has inputs the bag
lacks: the recorder received that update after the command and was stopped before writing
it (a cut bag; on a loaded machine an update may reach the recorder milliseconds after the
commands that name it). The check ends before the first such command's state and counts it
and every recorded command after it as not checked, naming the update, in its result line.

The check runs in lock-step, not in recorded time: each state is published once the live
controller has answered the previous one (again if no answer comes within 0.3 s: the
controller ignores a state it has already answered), each update 2 ms before the next
state. The controller takes ``dt`` from the states' stamps, so the pace does not matter,
and its depth-1 best-effort state queue cannot drop a state (at recorded speed on 2 cores
it dropped 2-3 %, each drop changing the next ~8 commands by up to 0.1 N). Then the
controller computes bit for bit the same commands (measured: 0 difference over 1966
commands of a 2 s fig8 run); any difference means the control code changed.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from haptic_topology.bag.controller_check import CheckResult, CommandCheck, controller_plan
from haptic_topology.bag.reader import (
    open_bag,
)
from haptic_topology.bag.replay import (
    COMMAND,
    DEFAULT_TOLERANCE,
    ReplayStats,
    left_out,
    plan,
)
from haptic_topology.errors import BagError, ReplayError
from haptic_topology.nodes.bag_publishers import Publishers
from haptic_topology.nodes.dds_env import localhost_discovery_default
from haptic_topology.nodes.node_thread import NodeThread
from haptic_topology.vocabulary import TOPIC_LMI_ACK, TOPIC_STATE


def _spinner(name: str, namespace: str = '') -> NodeThread:
    """The replay's node, in an rclpy context of its own, spun in a thread; DDS set up as the
    nodes set it up (``run_main``)."""
    localhost_discovery_default(os.environ)
    return NodeThread(name, 'replay_spin', own_context=True, namespace=namespace)


def replay(bag_path: str | Path, rate: float = 1.0, topics: Sequence[str] | None = None,
           loop: bool = False, start_offset: float = 0.0, wait_subscribers: float = 0.0,
           stop: threading.Event | None = None, namespace: str = '') -> ReplayStats:
    """Plain replay (see module doc), topics under ``namespace`` (except /diagnostics);
    returns what was published."""
    bag = open_bag(bag_path)
    items = plan(bag, topics, start_offset)
    spinner = _spinner('haptic_replay')
    try:
        pubs = Publishers(spinner.node, bag, items.topics, namespace)
        if wait_subscribers > 0:
            pubs.wait_for_subscribers(pubs.pubs, wait_subscribers)
        stats = pubs.publish(items, items.span, rate, loop, stop)
        stats.unacknowledged = pubs.wait_acked()
        stats.left_out = [] if topics else sorted(left_out(bag))
        return stats
    finally:
        spinner.close()


def check_controller(bag_path: str | Path, params: Path,
                     scenario: str | None = None, tolerance: float = DEFAULT_TOLERANCE,
                     startup_timeout: float = 40.0, log_dir: Path | None = None) -> CheckResult:
    """The controller regression check (see module doc)."""
    from haptic_topology.nodes.qos import QOS_LMI
    bag = open_bag(bag_path)
    cp = controller_plan(bag)
    scenario = scenario or cp.scenario
    if not scenario:
        raise BagError(f'{bag.path}: no scenario in metadata.yaml custom_data; give '
                       '--scenario')
    ns = f'/replay_{os.getpid()}_{int(time.time() * 1e3) % 100000}'
    logs = Path(log_dir or tempfile.mkdtemp(prefix='haptic_replay_'))
    logs.mkdir(parents=True, exist_ok=True)
    log = logs / 'lmi_controller.log'
    argv = [sys.executable, '-m', 'haptic_topology.nodes.lmi_controller', '--ros-args',
            '--params-file', str(params), '-p', f'scenario:={scenario}', '-p',
            f'mode:={cp.mode}', '-p', 'ack_updates:=true', '-r', f'__ns:={ns}']
    if cp.graph_id:             # the recorded graph's (none: the default graph)
        argv[-2:-2] = ['-p', f'graph_id:={cp.graph_id}']
    check = CommandCheck(cp)
    # The controller takes updates from the VE of its graph only and states from its driver
    # (nodes named ve_sim and device_driver in its namespace): the check plays both parts.
    spinner = _spinner('ve_sim', ns)
    try:
        driver = _spinner('device_driver', ns)
    except BaseException:
        spinner.close()
        raise
    with log.open('wb') as handle:
        proc = subprocess.Popen(argv, stdout=handle, stderr=subprocess.STDOUT,
                                env=dict(os.environ, PYTHONUNBUFFERED='1'),
                                start_new_session=True)
        try:
            from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

            from haptic_topology_msgs.msg import DeviceCommand

            answered = threading.Condition()

            def keep(msg: Any) -> None:
                with answered:
                    check.answer(int(msg.state_seq), int(msg.mode), msg.wrench)
                    answered.notify_all()

            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                             reliability=ReliabilityPolicy.BEST_EFFORT)
            sub = spinner.node.create_subscription(DeviceCommand, f'{ns}/{COMMAND}', keep,
                                                   qos)
            acked: dict[int, int] = {}

            def ack(msg: Any) -> None:
                with answered:
                    acked[int(msg.data)] = acked.get(int(msg.data), 0) + 1
                    answered.notify_all()

            from std_msgs.msg import UInt64

            spinner.node.create_subscription(UInt64, f'{ns}/{TOPIC_LMI_ACK}', ack, QOS_LMI)
            pubs = Publishers(spinner.node, bag, cp.topics, ns, {TOPIC_STATE: driver.node})
            deadline = time.monotonic() + startup_timeout
            while sub.get_publisher_count() == 0 and time.monotonic() < deadline:
                if proc.poll() is not None:
                    raise ReplayError(f'lmi_controller exited with {proc.returncode}: '
                                      f'{log.read_text(errors="replace")[-800:]}')
                time.sleep(0.05)
            pubs.wait_for_subscribers(pubs.pubs, max(deadline - time.monotonic(), 0.1))
            stats = pubs.publish_lockstep(cp.items(), answered, check, acked)
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(10.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            spinner.close()
            driver.close()
    return check.result(tolerance, scenario, stats)


def run(args: argparse.Namespace) -> int:
    """The ``replay`` subcommand (see module doc)."""
    rate = float(args.rate)
    if not (rate > 0 and math.isfinite(rate)):
        raise BagError(f'--rate: expected a positive factor, got {rate}')
    if args.start_offset < 0:
        raise BagError(f'--start-offset: expected seconds >= 0, got {args.start_offset}')
    if args.check_controller:
        from haptic_topology.paths import config_dir

        params = args.params or config_dir() / 'haptic_topology.yaml'
        res = check_controller(args.bag, params, args.scenario, args.tolerance)
        print(res.stats.line())
        print(res.line())
        return 0 if res.ok else 1
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    stats = replay(args.bag, rate, args.topics, args.loop, args.start_offset,
                   args.wait_subscribers, stop, args.namespace)
    print(stats.line())
    return 0


