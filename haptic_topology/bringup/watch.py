"""See the node graph the way ROS tools do: lifecycle states, diagnostics and graph counts.

The bringup (``haptic-topology run``), replay and the test harness wait on these, never on log
lines or sleeps: the recorder's ``/diagnostics`` status (``connected``: matched to the loop's
publishers), ``device_driver``'s lifecycle state (``/device_driver/get_state``: ``active``
while the loop runs, ``inactive`` after ``run_duration``) and publisher/subscriber counts.
Every wait has a deadline and raises :class:`WaitTimeout` naming what did not happen.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from haptic_topology.bringup.options import FOXGLOVE_NODE, NODES
from haptic_topology.errors import TransitionRefused, WaitTimeout
from haptic_topology.vocabulary import (
    STATUS_CONTROLLER,
    STATUS_DEVICE,
    STATUS_RECORDER,
    STATUS_VE,
    TOPIC_COMMAND,
    TOPIC_HAND_INPUTS,
    TOPIC_LMI,
    TOPIC_STATE,
    TOPIC_TYPES,
    TOPIC_VT_PATH,
    Clock,
    QosRole,
    publisher_role,
)

#: ``/diagnostics`` status names of the graph's nodes.
RECORDER_STATUS = STATUS_RECORDER
DEVICE_STATUS = STATUS_DEVICE
VE_STATUS = STATUS_VE
CONTROLLER_STATUS = STATUS_CONTROLLER


#: ``DiagnosticStatus.ERROR``.
ERROR = 2


#: Node names of a graph's processes (in the root namespace): a reader of a loop topic under
#: another name is another program's (see :meth:`GraphWatcher.unmatched`).
GRAPH_NODES = frozenset((*NODES, FOXGLOVE_NODE))


def graph_node(name: str, namespace: str) -> bool:
    """Whether the node ``namespace``/``name`` is one of a graph's: one of
    :data:`GRAPH_NODES` or a hidden reader node of one (``_<node>_<suffix>``,
    :mod:`haptic_topology.nodes.take`), in the root namespace."""
    return namespace == '/' and (name in GRAPH_NODES
                                 or any(name.startswith(f'_{n}_') for n in GRAPH_NODES))


def loop_readers(layout: str) -> dict[tuple[str, str], int]:
    """``(status name, topic) -> readers``: the graph's DDS readers of each publisher of the
    run's recorded topics in ``layout`` (``hosted`` or ``separate``), the recorder's included
    (what :meth:`GraphWatcher.unmatched` expects to see).

    The LMI updates go to the controller (hosted: in the device driver's process) and the
    recorder, the VE's path to the recorder, the hand inputs to the VE and the recorder, the
    commands to the recorder and, in the separate layout, to the device driver (hosted, it
    takes none from DDS), the device's states to the recorder and, in the separate layout,
    the controller: matched before the driver is activated, since its first states,
    published before it engages, are in the bag too.
    """
    hosted = layout != 'separate'
    return {(VE_STATUS, TOPIC_LMI): 2, (VE_STATUS, TOPIC_VT_PATH): 1,
            (CONTROLLER_STATUS, TOPIC_HAND_INPUTS): 2,
            (CONTROLLER_STATUS, TOPIC_COMMAND): 1 if hosted else 2,
            (DEVICE_STATUS, TOPIC_STATE): 1 if hosted else 2}


def loop_writers(layout: str) -> dict[tuple[str, str], int]:
    """``(status name, topic) -> writers``: the graph's DDS writers that each subscription
    of the loop's inputs takes in ``layout`` (``hosted`` or ``separate``), matched on the
    subscription's side before the driver is activated (what
    :meth:`GraphWatcher.unmatched_readers` expects to see).

    The VE takes the controller's hand inputs, the controller the VE's LMI updates and, in
    the separate layout, the device's states, and the device driver the controller's
    commands."""
    hosted = layout != 'separate'
    return {(VE_STATUS, TOPIC_HAND_INPUTS): 1, (CONTROLLER_STATUS, TOPIC_LMI): 1,
            **({} if hosted else {(CONTROLLER_STATUS, TOPIC_STATE): 1,
                                  (DEVICE_STATUS, TOPIC_COMMAND): 1})}


#: Consecutive equal recorder reports that count as settled (0.25 s apart).
SETTLE_REPORTS = 5


_TYPES_LOCK = threading.Lock()
_types_imported = False


def import_type_supports() -> None:
    """Import the type support of every message and service a :class:`GraphWatcher` uses,
    once per process, under a lock.

    rosidl's generated ``__import_type_support__`` is not thread-safe: a service's type
    support is set before its request's converters, so a thread that creates a client
    meanwhile sends with a converter still None (``TypeError: Object of type 'NoneType' is
    not an instance of 'capsule'`` in ``Client.call_async``). Seen once in a stress run of
    the tests, which run eight graphs from eight threads of one process.
    """
    global _types_imported
    with _TYPES_LOCK:
        if _types_imported:
            return
        from diagnostic_msgs.msg import DiagnosticArray
        from lifecycle_msgs.msg import Transition, TransitionEvent
        from lifecycle_msgs.srv import ChangeState, GetState
        from rclpy.type_support import check_for_type_support

        for t in (DiagnosticArray, Transition, TransitionEvent, ChangeState,
                  ChangeState.Request, ChangeState.Response, GetState, GetState.Request,
                  GetState.Response):
            check_for_type_support(t)
        _types_imported = True


class GraphWatcher:
    """An rclpy node of its own (own context) that watches the graph; use as a context
    manager. ``alive``: called while waiting, raises if a process of the graph has died;
    ``args``: ROS arguments of its context (default none: never the command line, whose
    ``-p NODE:NAME:=VALUE`` items are the nodes', not the watcher's)."""

    def __init__(self, name: str = 'haptic_watch', alive: Callable[[], None] | None = None,
                 args: list[str] | None = None,
                 lifecycle_nodes: tuple[str, ...] = ('device_driver',),
                 domain_id: int | None = None, graph_id: str | None = None) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from lifecycle_msgs.srv import GetState
        from rclpy.executors import SingleThreadedExecutor

        from haptic_topology.nodes.dds_env import localhost_discovery_default
        from haptic_topology.nodes.qos import QOS_DIAGNOSTICS
        from haptic_topology.vocabulary import (
            TOPIC_COMMAND,
            TOPIC_DIAGNOSTICS,
            TOPIC_HAND_INPUTS,
            TOPIC_STATE,
            TOPIC_VT_PATH,
        )

        import_type_supports()
        self._rclpy = rclpy
        localhost_discovery_default(os.environ)   # the nodes' DDS setup (run_main)
        self.context = rclpy.Context()
        args = [] if args is None else args
        if domain_id is None:
            rclpy.init(context=self.context, args=args)
        else:
            rclpy.init(context=self.context, args=args, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.alive = alive or (lambda: None)
        #: The graph watched (None: any): statuses naming another ``graph_id`` are not read.
        self.graph_id = graph_id
        self.status: dict[str, dict[str, str]] = {}
        #: Per status name: the newest report's level (0 OK, 1 WARN, 2 ERROR, 3 STALE),
        #: message and hardware_id.
        self.report: dict[str, tuple[int, str, str]] = {}
        #: Topics whose recorded counts stop growing once the loop has stopped (the hand
        #: inputs a little after the states: the controller flushes its last partial batch).
        self.settle_topics = (TOPIC_STATE, TOPIC_COMMAND,
                              TOPIC_HAND_INPUTS, TOPIC_VT_PATH)
        self.node.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS,
                                      self._on_diagnostics, QOS_DIAGNOSTICS)
        self._get_state = GetState
        self._clients: dict[str, Any] = {}
        self._recorder_counts: list[dict[str, str]] = []
        #: Newest lifecycle state label seen per node (transition events, or get_state).
        self.lifecycle: dict[str, str] = {}
        from lifecycle_msgs.msg import TransitionEvent
        for n in lifecycle_nodes:
            self.node.create_subscription(TransitionEvent, f'/{n}/transition_event',
                                          self._on_transition(n), 10)

    def __enter__(self) -> GraphWatcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)

    def _on_transition(self, node: str) -> Callable[[Any], None]:
        def on_event(msg: Any) -> None:
            self.lifecycle[node] = str(msg.goal_state.label)
        return on_event

    def _on_diagnostics(self, msg: Any) -> None:
        for st in msg.status:
            values = {kv.key: kv.value for kv in st.values}
            if self.graph_id is not None and values.get('graph_id',
                                                        self.graph_id) != self.graph_id:
                continue
            if st.name == RECORDER_STATUS:
                # The run's topics only: keep-alive updates, visualisation and diagnostics
                # go on after the run.
                self._recorder_counts.append({k: v for k, v in values.items()
                                              if k.startswith('received ')
                                              and k.endswith(self.settle_topics)})
                del self._recorder_counts[:-SETTLE_REPORTS]
            self.status[st.name] = values
            level = st.level[0] if isinstance(st.level, bytes) else int(st.level)
            self.report[st.name] = (level, str(st.message), str(st.hardware_id))

    def spin(self, seconds: float) -> None:
        self.executor.spin_once(timeout_sec=seconds)

    def wait(self, cond: Callable[[], bool], timeout: float,
             what: str | Callable[[], str]) -> float:
        """Spin until ``cond()``; return the monotonic time it held. ``what`` (or what it
        returns then) names the condition in the :class:`WaitTimeout`."""
        deadline = time.monotonic() + timeout
        while not cond():
            self.alive()
            if time.monotonic() > deadline:
                raise WaitTimeout(f'{what if isinstance(what, str) else what()}: not within '
                                  f'{timeout:g} s')
            self.spin(0.02)
        return time.monotonic()

    # -- what to wait for --------------------------------------------------------------------
    def recorder_connected(self) -> bool:
        return self.status.get(RECORDER_STATUS, {}).get('connected') == 'true'

    def writers_matched(self, readers: Mapping[tuple[str, str], int],
                        clock: Clock = Clock.WALL,
                        at_least: Mapping[tuple[str, str], int] | None = None) -> bool:
        """Every publisher ``(status name, topic)`` of ``readers`` is matched to its readers
        (:meth:`unmatched` is empty).

        The recorder's ``connected`` says its readers matched the writers; DDS matches the two
        sides separately (each on the other's announcement), and a reliable writer sends only
        to the readers it has matched, so a loop started on the recorder's side alone could
        lose the run's first messages of a topic in the bag."""
        return not self.unmatched(readers, clock, at_least)

    def readers_matched(self, writers: Mapping[tuple[str, str], int],
                        clock: Clock = Clock.WALL) -> bool:
        """Every subscription ``(status name, topic)`` of ``writers`` is matched to its
        writers (:meth:`unmatched_readers` is empty).

        The other side of :meth:`writers_matched`: a reliable writer that has matched a reader
        sends to it, but a reader that has not matched the writer yet drops what comes and
        gets it only later, when the writer repairs it. Meanwhile a message of another
        writer that the reader did match (another program that copies the graph's id and
        echoes its messages) is taken first, and the graph's own then counts as a copy of it:
        in lock-step the VE refused the controller's first hand inputs that way, and the run
        waited for ever."""
        return not self.unmatched_readers(writers, clock)

    def unmatched(self, readers: Mapping[tuple[str, str], int],
                  clock: Clock = Clock.WALL,
                  at_least: Mapping[tuple[str, str], int] | None = None) -> list[str]:
        """The publishers ``(status name, topic)`` of ``readers`` not yet matched to their
        readers, each as one line. A publisher is matched when its node reports (``matched
        <topic>`` in its ``/diagnostics``) at least as many DDS readers as this watcher sees
        readers of the topic that it matches (the topic's type; a QoS the graph's publisher
        under ``clock`` offers) and at least ``at_least`` of it (any readers), and when this
        watcher sees the number in ``readers`` under the graph's node names
        (:func:`graph_node`).

        A writer's count says how many readers it matched, not which: another program's
        reader (a second graph's, ``ros2 topic echo``) counts as much as the graph's own, and a
        count alone would let it stand in for one that is not matched yet (in lock-step, the
        VE's hand inputs lost before it matched, and the run waiting for an update forever).
        What this leaves open: a reader that the publisher matches before this watcher sees
        it, i.e. one that appears during the start-up (the watcher starts before the graph's
        nodes, so it sees the readers that were there before them first)."""
        return self._unmatched(readers, clock, at_least or {}, 'readers')

    def unmatched_readers(self, writers: Mapping[tuple[str, str], int],
                          clock: Clock = Clock.WALL) -> list[str]:
        """The subscriptions ``(status name, topic)`` of ``writers`` not yet matched to
        their writers, each as one line: as :meth:`unmatched`, with the writers of the topic
        that the subscription matches (the QoS it requests: the graph's publisher's under
        ``clock``) and ``writers`` of them under the graph's node names."""
        return self._unmatched(writers, clock, {}, 'writers')

    def _unmatched(self, expected: Mapping[tuple[str, str], int], clock: Clock,
                   at_least: Mapping[tuple[str, str], int], peers: str) -> list[str]:
        out = []
        for (name, topic), n in expected.items():
            got = int(self.status.get(name, {}).get(f'matched {topic}', '0'))
            own, others = self._peers(topic, publisher_role(topic, clock), peers)
            need = max(n, at_least.get((name, topic), 0), own + len(others))
            if own < n or got < need:
                out.append(f'{name}: {topic} matched to {got} {peers} of {need} (seen: {own} '
                           f'of the graph, expected {n}; others: {", ".join(others) or "none"})')
        return out

    def _peers(self, topic: str, role: QosRole, peers: str) -> tuple[int, list[str]]:
        """The DDS ``peers`` (``readers`` or ``writers``) of ``topic`` this watcher sees that
        an endpoint of the graph's with QoS ``role`` matches: how many the graph's nodes have,
        and the others' node names. A reader matches a writer unless it asks for more than
        the writer offers: reliable of a best-effort writer, transient local of a volatile
        one."""
        from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

        name = f'/{topic.lstrip("/")}'
        infos = (self.node.get_subscriptions_info_by_topic(name) if peers == 'readers'
                 else self.node.get_publishers_info_by_topic(name))
        own, others = 0, []
        for info in infos:
            q = info.qos_profile
            reliable = q.reliability == ReliabilityPolicy.RELIABLE
            latched = q.durability == DurabilityPolicy.TRANSIENT_LOCAL
            if peers == 'readers':          # the peer asks, the graph's publisher offers
                matches = (not reliable or role.reliable) and (not latched
                                                               or role.transient_local)
            else:                           # the graph's subscription asks, the peer offers
                matches = (reliable or not role.reliable) and (latched
                                                               or not role.transient_local)
            if info.topic_type != TOPIC_TYPES.get(topic, info.topic_type) or not matches:
                continue            # never matched: another type, or QoS that do not match
            if graph_node(info.node_name, info.node_namespace):
                own += 1
            else:
                others.append(f'{info.node_namespace.rstrip("/")}/{info.node_name}')
        return own, others

    def recorder_settled(self) -> bool:
        """The recorder reported the same counts of the run's topics ``SETTLE_REPORTS`` times
        in a row (its status comes every 0.25 s, so for 1 s): it has taken everything the
        loop sent."""
        h = self._recorder_counts
        return (len(h) == SETTLE_REPORTS and all(c == h[-1] for c in h)
                and any(v != '0' for v in h[-1].values()))

    def recorder_has_the_run(self, reliable_loop: bool) -> bool:
        """The bag holds everything the run sent, by the nodes' own counts (no timing):
        the device's loop has stopped (``loop_running`` false: its ``sent`` count of states
        is final), the controller has nothing pending (``hand_pending`` 0) and, when the
        loop topics are reliable (``reliable_loop``, lock-step), has seen the last state
        (so its counts are final too), the VE has consumed the last hand input the
        controller sent and sent every path sample, and the recorder received as many
        messages of each reliable topic as were sent (at least as many: a foreign publisher
        adds to the recorder's count). With best-effort loop topics (wall
        clock) states and commands may be lost on the way: only the reliable topics are
        compared, and the recorder's counts must also have settled."""

        dev = self.status.get(DEVICE_STATUS, {})
        ctl = self.status.get(CONTROLLER_STATUS, {})
        ve = self.status.get(VE_STATUS, {})
        rec = self.status.get(RECORDER_STATUS, {})
        hand = ctl.get(f'sent {TOPIC_HAND_INPUTS}')
        # The VE has taken the last hand input sent (by its seq: a batch that DDS dropped on
        # a starved VE, counted in its lost_hand_inputs, never comes).
        last = ctl.get('hand_last_seq')
        if (dev.get('loop_running') != 'false' or ctl.get('hand_pending') != '0'
                or last is None or ve.get('hand_last_seq') != last
                or ve.get('path_pending') != '0'):
            return False
        sent = {TOPIC_HAND_INPUTS: hand,
                TOPIC_VT_PATH: ve.get(f'sent {TOPIC_VT_PATH}')}
        if reliable_loop:
            if ctl.get('last_state_seq') != dev.get('seq'):
                return False
            sent[TOPIC_STATE] = dev.get(f'sent {TOPIC_STATE}')
            sent[TOPIC_COMMAND] = ctl.get(f'sent {TOPIC_COMMAND}')
        elif not self.recorder_settled():
            return False
        received = {k.removeprefix('received ').lstrip('/'): int(v) for k, v in rec.items()
                    if k.startswith('received ') and v.isdigit()}
        # At least as many: another publisher on a topic (a test's impostor) adds to it.
        return all(n is not None and n.isdigit()
                   and received.get(t.lstrip('/'), -1) >= int(n) for t, n in sent.items())

    def hand_inputs_rejected(self) -> str | None:
        """Why the run cannot stand, in one line, once ``ve_sim`` reports hand input batches
        of this graph whose contents it rejected (``rejected_hand_batches``, the first one's
        reason in ``hand_rejection``); None while it reports none. The VE never integrates a
        rejected batch's inputs, so the VT from then on is not the loop's: the run must end
        on this, not wait for the VE to take inputs it has refused. (Well-formed batches
        that the VE's admission refuses as another sender's are not counted there: the run
        goes on without them.)"""
        ve = self.status.get(VE_STATUS, {})
        count = ve.get('rejected_hand_batches', '0')
        if not count.isdigit() or int(count) == 0:
            return None
        n = int(count)
        reason = ve.get('hand_rejection') or 'its reason not reported'
        return (f've_sim rejected {n} hand input batch{"es" if n > 1 else ""} (the first: '
                f'{reason}); the VE did not take their inputs, so the run was stopped')

    def run_counts(self) -> dict[str, dict[str, str]]:
        """What :meth:`recorder_has_the_run` compares, as the nodes last reported it."""
        keys = ('loop_running', 'seq', 'hand_pending', 'last_state_seq', 'path_pending',
                'hand_last_seq', 'lost_hand_inputs')
        return {name: {k: v for k, v in values.items()
                       if k in keys or k.startswith(('sent ', 'received '))}
                for name, values in self.status.items()}

    def recorder_sees(self, topic: str) -> bool:
        """The recorder reports a publisher matched on ``topic`` (state or command)."""
        status = self.status.get(RECORDER_STATUS, {})
        return int(status.get(f'publishers {topic}', '0')) > 0

    def change_state(self, node: str, transition: str, timeout: float = 10.0) -> None:
        """Ask ``node``'s lifecycle to make ``transition`` ('configure', 'activate', ...);
        raise :class:`WaitTimeout` if it is not answered, or not done, in time."""
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        client = self.node.create_client(ChangeState, f'/{node}/change_state')
        try:
            self.wait(client.service_is_ready, timeout, f'{node}: change_state service')
            req = ChangeState.Request()
            req.transition.id = getattr(Transition, f'TRANSITION_{transition.upper()}')
            future = client.call_async(req)
            self.wait(future.done, timeout, f'{node}: {transition}')
            if not future.result().success:
                raise TransitionRefused(f'{node}: transition {transition} failed')
        finally:
            self.node.destroy_client(client)

    def error_message(self, name: str, timeout: float) -> str:
        """The message of status ``name`` once it reports ERROR (a node that refused a
        transition publishes its reason so), without a leading ``fault:``; '' when it has not
        within ``timeout`` s."""
        try:
            self.wait(lambda: self.report.get(name, (0, '', ''))[0] == ERROR, timeout,
                      f'{name} at ERROR')
        except WaitTimeout:
            return ''
        return self.report[name][1].removeprefix('fault: ')

    def lifecycle_state(self, node: str, timeout: float = 2.0) -> str:
        """The label of ``node``'s lifecycle state ('' when its service does not answer)."""
        client = self._clients.get(node)
        if client is None:
            client = self.node.create_client(self._get_state, f'/{node}/get_state')
            self._clients[node] = client
        if not client.service_is_ready():
            return ''
        future = client.call_async(self._get_state.Request())
        deadline = time.monotonic() + timeout
        while not future.done() and time.monotonic() < deadline:
            self.spin(0.01)
        if not future.done():
            return ''
        return str(future.result().current_state.label)

    def wait_lifecycle(self, node: str, labels: tuple[str, ...], timeout: float,
                       poll: float = 2.0) -> float:
        """Wait until ``node`` is in one of the lifecycle states ``labels``.

        Transition events (``~/transition_event``) are the signal; ``get_state`` is asked
        only every ``poll`` s, for events sent before this watcher was matched: serving that
        service at 20 Hz cost the 1 kHz loop of the driver half its answered cycles.
        """
        deadline = time.monotonic() + timeout
        next_poll = time.monotonic()
        while True:
            if time.monotonic() >= next_poll:
                label = self.lifecycle_state(node)
                if label:
                    self.lifecycle[node] = label
                next_poll = time.monotonic() + poll
            if self.lifecycle.get(node) in labels:
                return time.monotonic()
            self.alive()
            if time.monotonic() > deadline:
                raise WaitTimeout(f'{node}: lifecycle state '
                                  f'{self.lifecycle.get(node) or "(no answer)"}, not '
                                  f'{" or ".join(labels)} within {timeout:g} s')
            self.spin(0.05)

    def subscribers(self, topic: str) -> int:
        return int(self.node.count_subscribers(topic))

    def publishers(self, topic: str) -> int:
        return int(self.node.count_publishers(topic))
