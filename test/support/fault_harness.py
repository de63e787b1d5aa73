"""Fault injection on the real node graph: one run, several faults one after the other.

Starts recorder, ve_sim, lmi_controller and device_driver as four processes (the separate
layout, ``device_driver.host_controller: false``; scenario ``circle``:
the hand drags the device around a circle, so the loop is busy the whole time), then, each
at a logged wall-clock time (the header stamps are wall-clock ROS time too):

1. ``watchdog``: SIGSTOP lmi_controller for 100 ms (commands stop), SIGCONT;
2. ``bad_messages``: 0.5 s of malformed messages from this process on every input topic
   (NaN, wrong sizes, wrong task_dim / dof, non-SPD mass matrix, unknown mode, hand input
   batches with a huge wrench, a NaN, a short pose or fewer state seqs than seqs) plus
   finite commands of 1e9 N answering real device states, twice per state: with the id of
   the controller the device follows, copied from the driver's ``/diagnostics`` (identity is
   not authentication: these reach the device and must be clamped), and with another id
   (rejected as foreign);
3. ``ve_stop``: SIGSTOP ve_sim for 1 s, SIGCONT (stale LMI, degrade, re-sync);
4. ``kill_ve``, ``kill_controller``, ``kill_device``: SIGKILL the node and start it again;
5. ``ve_gone``: stop ve_sim (Ctrl-C) while this process keeps a publisher on ``lmi/update``:
   the controller cannot tell its graph's updates from foreign ones and fades to zero; then
   start ve_sim again;
6. ``kill_recorder``: SIGKILL the recorder and start it again (into a second bag).

Then stops everything and reads both bags. Used by ``test_fault_injection.py``;
``python test/support/fault_harness.py`` runs it and prints the README table.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from haptic_topology import vocabulary as vocab
from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.paths import config_dir
from haptic_topology.processes import terminate

PARAMS = config_dir() / 'haptic_topology.yaml'
SCENARIO = 'circle'
#: Longest wait (s) for the graph to do what it should (start, engage, recover): generous, so
#: a slow or loaded machine runs the sequence slower, never differently.
WAIT = 90.0
WATCHDOG, IDLE = 4, 16
#: seq / state_seq of every message the injector publishes (so the analysis can tell them apart).
INJECTED_SEQ = 10 ** 9
#: The controller id of the injector's foreign commands (not a controller's random one).
FOREIGN_ID = 2 ** 62 + 54321


@dataclass
class Proc:
    name: str
    popen: subprocess.Popen[bytes]
    log: Path
    handle: IO[bytes]

    def text(self) -> str:
        try:
            return self.log.read_text(encoding='utf-8', errors='replace')
        except OSError:
            return ''


@dataclass
class FaultRun:
    """What happened (wall-clock event times) and what the bags hold."""

    out: Path
    events: dict[str, tuple[float, float]] = field(default_factory=dict)  # name: (t0, t1)
    bags: list[Path] = field(default_factory=list)
    logs: dict[str, str] = field(default_factory=dict)
    exit_codes: dict[str, int] = field(default_factory=dict)
    injected: dict[str, int] = field(default_factory=dict)
    #: Seconds from the end of a fault (the kill, for kills) until the nodes reported the loop
    #: back on /diagnostics (what the harness waited for).
    recovered: dict[str, float] = field(default_factory=dict)
    # From the bags:
    states: list[list[Any]] = field(default_factory=list)  # per bag, in arrival order
    commands: list[Any] = field(default_factory=list)
    hands: list[list[Any]] = field(default_factory=list)    # HandInputs, per bag
    updates: list[Any] = field(default_factory=list)
    diagnostics: dict[str, dict[str, float]] = field(default_factory=dict)  # max per key
    truncated: list[Path] = field(default_factory=list)


class Graph:
    """The node processes, restartable one by one."""

    def __init__(self, out: Path, mode: str = 'penalty') -> None:
        self.out = out
        self.logs = out / 'logs'
        self.logs.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, Proc] = {}
        self.starts: dict[str, int] = {}
        self.mode = mode
        self.bags: list[Path] = []

    def start(self, name: str) -> Proc:
        n = self.starts.get(name, 0) + 1
        self.starts[name] = n
        args = ['--ros-args', '--params-file', str(PARAMS), '-p', f'scenario:={SCENARIO}',
                '-p', f'lmi_controller:mode:={self.mode}', '-p',
                # controller, recorder and this process's injector must see the device
                # before it engages, so the bag holds the loop from its first state
                'device_driver:min_subscribers:=3',
                # the separate layout: each node its own process, killed and restarted alone
                '-p', 'device_driver:host_controller:=false']
        if name == 'recorder':
            bag = self.out / f'bag{n}'
            self.bags.append(bag)
            args += ['-p', f'recorder:output:={bag}']
        log = self.logs / f'{name}.{n}.log'
        handle = log.open('wb')
        popen = subprocess.Popen(
            [sys.executable, '-m', f'haptic_topology.nodes.{name}', *args], stdout=handle,
            stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED='1'),
            start_new_session=True)
        proc = Proc(name, popen, log, handle)
        self.procs[name] = proc
        return proc

    def check_alive(self) -> None:
        for p in self.procs.values():
            if p.popen.poll() is not None and p.popen.returncode not in (-9,):
                raise RuntimeError(f'{p.name} exited ({p.popen.returncode}):\n'
                                   f'{p.text()[-2000:]}')

    def signal(self, name: str, sig: int) -> None:
        self.procs[name].popen.send_signal(sig)

    def pause(self, name: str, seconds: float) -> tuple[float, float]:
        """SIGSTOP ``name`` for ``seconds``; return the (stop, continue) wall times."""
        t0 = time.time()
        self.signal(name, signal.SIGSTOP)
        time.sleep(seconds)
        self.signal(name, signal.SIGCONT)
        return t0, time.time()

    def stop(self, name: str) -> int:
        """Stop ``name`` as Ctrl-C does (its endpoints leave the graph at once) and forget
        it until :meth:`start`."""
        p = self.procs.pop(name)
        code = terminate(p.popen, 10.0, 3.0)
        p.handle.close()
        return code

    def kill(self, name: str) -> int:
        p = self.procs[name]
        p.popen.send_signal(signal.SIGKILL)
        code = p.popen.wait(10)
        p.handle.close()
        return code

    def stop_all(self) -> dict[str, int]:
        codes: dict[str, int] = {}
        for name in ('device_driver', 'lmi_controller', 've_sim', 'recorder'):
            p = self.procs.get(name)
            if p is None:
                continue
            if p.popen.poll() is None:
                p.popen.send_signal(signal.SIGCONT)
            codes[name] = terminate(p.popen, 10.0, 3.0)
            p.handle.close()
        return codes


class Injector:
    """Publishes malformed messages from this process (its own rclpy context)."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        from haptic_topology.nodes.qos import QOS_DIAGNOSTICS, QOS_HAND_INPUTS, QOS_LMI, QOS_LOOP
        from haptic_topology.vocabulary import (
            TOPIC_COMMAND,
            TOPIC_DIAGNOSTICS,
            TOPIC_HAND_INPUTS,
            TOPIC_LMI,
            TOPIC_STATE,
        )
        from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('fault_injector', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        n = self.node
        self.cmd_pub = n.create_publisher(DeviceCommand, TOPIC_COMMAND, QOS_LOOP)
        self.state_pub = n.create_publisher(DeviceState, TOPIC_STATE, QOS_LOOP)
        self.lmi_pub = n.create_publisher(LmiUpdate, TOPIC_LMI, QOS_LMI)
        self.hand_pub = n.create_publisher(HandInputs, TOPIC_HAND_INPUTS,
                                           QOS_HAND_INPUTS)
        self.types = (DeviceCommand, DeviceState, HandInputs, LmiUpdate)
        self.counts: dict[str, int] = {}
        self._huge = False
        self._followed = 0                       # the controller id the device follows
        self._n_state = 0
        self._bad_commands: dict[str, dict[str, Any]] = {}
        self._bad_keys: list[str] = []
        n.create_subscription(DeviceState, TOPIC_STATE, self._on_state, QOS_LOOP)
        from diagnostic_msgs.msg import DiagnosticArray
        n.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, self._on_diagnostics,
                              QOS_DIAGNOSTICS)
        self.status: dict[str, dict[str, str]] = {}
        self.last_running_state = -math.inf      # monotonic time of the newest running state
        self.last_running_seq = 0                # and its seq

    def _on_diagnostics(self, msg: Any) -> None:
        for st in msg.status:
            self.status[st.name] = {'_message': st.message,
                                    **{kv.key: kv.value for kv in st.values}}

    def value(self, status: str, key: str, default: str = '') -> str:
        return self.status.get(status, {}).get(key, default)

    def wait(self, cond: Any, what: str, alive: Any, timeout: float = WAIT) -> float:
        """Spin until ``cond()`` (checking ``alive()``); return the wall time it held."""
        deadline = time.monotonic() + timeout
        while not cond():
            alive()
            if time.monotonic() > deadline:
                raise RuntimeError(f'{what}: not within {timeout:g} s; status {self.status}')
            self.executor.spin_once(timeout_sec=0.02)
        return time.time()

    def _count(self, key: str) -> None:
        self.counts[key] = self.counts.get(key, 0) + 1

    def _on_state(self, msg: Any) -> None:
        if not msg.status & IDLE and int(msg.seq) != INJECTED_SEQ:
            self.last_running_state = time.monotonic()
            self.last_running_seq = int(msg.seq)
        if self._huge and not msg.status & IDLE:
            cmd_t = self.types[0]
            for cid, key in ((self._followed, 'command_huge_finite'),
                             (FOREIGN_ID, 'command_huge_foreign')):
                self.cmd_pub.publish(cmd_t(state_seq=msg.seq, controller_id=cid, task_dim=3,
                                           mode=0, wrench=[1e9, -1e9, 1e3],
                                           vt_pose=list(msg.pose), vt_twist=list(msg.twist)))
                self._count(key)
            # One malformed command per state too (the driver's queue is 1 deep: a message
            # sent only every 10 ms may be overwritten before it is taken).
            key = self._bad_keys[self._n_state % len(self._bad_keys)]
            self._n_state += 1
            self.cmd_pub.publish(cmd_t(state_seq=msg.seq, **self._bad_commands[key]))
            self._count(key)

    def spin(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.005)

    def burst(self, seconds: float) -> None:
        """Every 10 ms one of each malformed message; huge finite commands on every state
        (module doc)."""
        followed = self.value('device_driver: loop', 'controller_id', '0')
        if not followed.isdigit() or int(followed) == 0:
            raise RuntimeError(f'the device driver reports no controller id: {followed!r}')
        self._followed = int(followed)
        cmd_t, state_t, hand_t, lmi_t = self.types
        nan = math.nan
        good_u = [1.0, 0.0, 0.0]
        bad_commands = {
            'command_nan': dict(task_dim=3, wrench=[nan, 0.0, 0.0]),
            'command_inf': dict(task_dim=3, wrench=[0.0, math.inf, 0.0]),
            'command_size': dict(task_dim=3, wrench=[1.0, 2.0]),
            'command_task_dim': dict(task_dim=6, wrench=good_u * 2),
            'command_mode': dict(task_dim=3, wrench=good_u, mode=9),
        }
        eye = np.eye(3)
        lmi_base = dict(dof=3, task_dim=3, q=[0.0] * 3, dq=[0.0] * 3,
                        mass_matrix=eye.ravel().tolist(), gravity=[0.0] * 3,
                        hand_jacobian=eye.ravel().tolist(), singular_values=[1.0] * 3,
                        left_singular_vectors=eye.ravel().tolist(), constraint_count=0,
                        constraint_weights=[0.0] * 3, characteristic_length=0.1,
                        hand_pose=[0.0] * 3, hand_twist=[0.0] * 3, seq=INJECTED_SEQ,
                        hand_input_seq=INJECTED_SEQ)
        bad_updates = {
            'update_dof': dict(lmi_base, dof=4),
            'update_nan': dict(lmi_base, q=[nan, 0.0, 0.0]),
            'update_size': dict(lmi_base, gravity=[0.0] * 2),
            'update_not_spd': dict(lmi_base, mass_matrix=(-eye).ravel().tolist()),
            'update_task_dim': dict(lmi_base, task_dim=6),
        }
        # Batches of two samples, each malformed in one field of one sample: rejected whole.
        from builtin_interfaces.msg import Time
        seqs = [INJECTED_SEQ, INJECTED_SEQ + 1]
        hand_base = dict(seq=seqs, state_seq=seqs, task_dim=3, stamp=[Time(), Time()],
                         pose=[0.0] * 6, twist=[0.0] * 6, hand_wrench=[0.0] * 6,
                         coupling_wrench=[0.0] * 6)
        bad_hands = {
            'hand_nan': dict(hand_base, hand_wrench=[0.0] * 3 + [nan, 0.0, 0.0]),
            'hand_huge': dict(hand_base, coupling_wrench=[1e7] + [0.0] * 5),
            'hand_size': dict(hand_base, pose=[0.0] * 4),
            'hand_count': dict(hand_base, state_seq=seqs[:1]),
        }
        bad_states = {
            'state_nan': dict(seq=INJECTED_SEQ, task_dim=3, pose=[nan, 0.0, 0.0], twist=[0.0] * 3,
                              hand_wrench=[0.0] * 3, applied_wrench=[0.0] * 3),
            'state_task_dim': dict(seq=INJECTED_SEQ, task_dim=2, pose=[0.0] * 2, twist=[0.0] * 2,
                                   hand_wrench=[0.0] * 2, applied_wrench=[0.0] * 2),
        }
        self._bad_commands = bad_commands
        self._bad_keys = list(bad_commands)
        self._huge = True
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            for key, kw in bad_commands.items():
                self.cmd_pub.publish(cmd_t(state_seq=1, **kw))
                self._count(key)
            for key, kw in bad_updates.items():
                self.lmi_pub.publish(lmi_t(**kw))
                self._count(key)
            for key, kw in bad_hands.items():
                self.hand_pub.publish(hand_t(**kw))
                self._count(key)
            for key, kw in bad_states.items():
                self.state_pub.publish(state_t(**kw))
                self._count(key)
            self.spin(0.01)
        self._huge = False

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


def run_faults(out: Path) -> FaultRun:
    """The fault sequence of the module doc. Each step waits for the graph to be back (the
    nodes' ``/diagnostics`` and the device's running states), with a generous deadline, so a
    slow machine runs the sequence slower, never differently."""
    return _run_faults(out)


def _run_faults(out: Path) -> FaultRun:
    run = FaultRun(out)
    g = Graph(out)
    injector: Injector | None = None
    ctl, dev, rec = 'lmi_controller: loop', 'device_driver: loop', 'recorder: bag'
    try:
        injector = Injector()
        inj = injector

        def wait(cond: Any, what: str) -> float:
            try:
                return inj.wait(cond, what, g.check_alive)
            except RuntimeError as exc:
                tails = '\n'.join(f'--- {p.log.name}:\n{p.text()[-1500:]}'
                                   for p in g.procs.values())
                raise RuntimeError(f'{exc}\nnode logs (tails):\n{tails}') from None

        def current(status: str, node: str) -> bool:
            # A report of the node's current process, not a late one of a killed process
            return inj.value(status, 'pid') == str(g.procs[node].popen.pid)

        def controller_back(key: str = '', least: int = 0) -> bool:
            return (current(ctl, 'lmi_controller') and inj.value(ctl, 'model') == 'fresh'
                    and inj.value(ctl, 'force_scale') == '1.000'
                    and (not key or int(inj.value(ctl, key, '0')) >= least))

        def engaged_since(t: float, below_seq: float = math.inf) -> bool:
            # below_seq: a restarted driver's states (its seq starts again at 1), not a
            # sample of the killed one still queued in this process
            return inj.last_running_state > t and inj.last_running_seq < below_seq

        g.start('recorder')
        wait(lambda: rec in inj.status, 'recorder reporting')
        g.start('ve_sim')
        g.start('lmi_controller')
        wait(lambda: inj.value(rec, 'connected') == 'true', 'recorder connected')
        t = time.monotonic()
        g.start('device_driver')
        wait(lambda: engaged_since(t), 'device engaged')
        injector.spin(1.0)

        trips = int(inj.value(dev, 'watchdog_trips', '0'))
        run.events['watchdog'] = g.pause('lmi_controller', 0.1)
        run.recovered['watchdog'] = wait(
            lambda: (int(inj.value(dev, 'watchdog_trips', '0')) > trips
                     and inj.value(dev, 'watchdog_scale') == '1.000'),
            'device tripped and faded back in') - run.events['watchdog'][1]
        injector.spin(1.0)

        t0 = time.time()
        injector.burst(0.5)
        run.events['bad_messages'] = (t0, time.time())
        injector.spin(1.0)

        run.events['ve_stop'] = g.pause('ve_sim', 1.0)
        inj.status.pop(ctl, None)
        run.recovered['ve_stop'] = wait(lambda: controller_back('degradations', 1),
                                        'controller re-synced after ve_stop'
                                        ) - run.events['ve_stop'][1]
        injector.spin(1.0)

        for name, back in (
                ('ve_sim', lambda: controller_back('ve_restarts', 1)),
                # A new controller is back once it answers the running loop (loop_seq: the
                # newest state it answered running), not when it has merely synced to the
                # VE's keep-alive updates (fresh model, full scale from its start): else,
                # on a loaded machine, the driver may be killed before the new controller
                # has seen it and it never counts a second device session. And the device
                # follows it: it took over from the killed controller's id.
                ('lmi_controller', lambda: controller_back('loop_seq', 1)
                 and int(inj.value(dev, 'controller_takeovers', '0')) >= 1),
                ('device_driver', lambda: controller_back('device_sessions', 2))):
            t0 = time.time()
            seq_killed = inj.last_running_seq
            g.kill(name)
            inj.status.pop(ctl, None)
            t = time.monotonic()
            g.start(name)
            if name == 'device_driver':
                inj.status.pop(dev, None)
                wait(lambda t=t, s=seq_killed: engaged_since(t, s), 'restarted device engaged')
            run.recovered[f'kill_{name}'] = wait(back, f'loop back after restarting {name}') - t0
            if name == 'device_driver':
                # The fault is over once the bag holds the new driver's states too: the
                # recorder matches its publisher when DDS's discovery gets there, which on a
                # loaded machine can come after the loop is back (traced: 0.5 s after). The
                # first report after the restart counts every state of the killed driver.
                received = f'received {vocab.TOPIC_STATE}'
                inj.status.pop(rec, None)
                wait(lambda: rec in inj.status, 'recorder reporting')
                seen = int(inj.value(rec, received, '0'))
                wait(lambda k=received, n=seen: int(inj.value(rec, k, '0')) > n,
                     "recorder receiving the restarted driver's states")
            run.events[f'kill_{name}'] = (t0, time.time())
            injector.spin(1.0)

        # The own VE gone (stopped, not restarted) while this process's injector keeps a
        # publisher on lmi/update: the controller cannot tell its graph's updates from
        # foreign ones, takes none, fades the force to zero and says why (ERROR).
        t0 = time.time()
        restarts = int(inj.value(ctl, 've_restarts', '0'))
        code = g.stop('ve_sim')
        assert code == 0, f've_sim stopped with {code}'
        wait(lambda: (current(ctl, 'lmi_controller')
                      and 'cannot be told' in inj.value(ctl, '_message')
                      and inj.value(ctl, 'force_scale') == '0.000'),
             'controller faded to zero, own VE gone beside a foreign publisher')
        run.events['ve_gone'] = (t0, time.time())
        g.start('ve_sim')
        run.recovered['ve_gone'] = wait(lambda: controller_back('ve_restarts', restarts + 1),
                                        'loop back after ve_sim returned') - t0
        injector.spin(1.0)

        t0 = time.time()
        g.kill('recorder')
        inj.status.pop(rec, None)
        g.start('recorder')
        run.recovered['kill_recorder'] = wait(lambda: current(rec, 'recorder')
                                              and inj.value(rec, 'connected') == 'true',
                                              'restarted recorder connected') - t0
        run.events['kill_recorder'] = (t0, time.time())
        injector.spin(1.0)
    finally:
        if injector is not None:
            run.injected = dict(injector.counts)
            injector.close()
        run.exit_codes = g.stop_all()
        run.logs = {p.log.name: p.text() for p in g.procs.values()}
        for log in sorted(g.logs.glob('*.log')):
            run.logs[log.name] = log.read_text(encoding='utf-8', errors='replace')
    run.bags = list(g.bags)
    _read_bags(run)
    return run


def _read_bags(run: FaultRun) -> None:
    decode = decoder()
    for path in run.bags:
        bag = open_bag(path)
        run.states.append([])
        run.hands.append([])
        for m in iter_messages(bag):
            if m.topic.endswith(vocab.TOPIC_STATE):
                run.states[-1].append(decode(m))
            elif m.topic.endswith(vocab.TOPIC_COMMAND):
                run.commands.append(decode(m))
            elif m.topic.endswith(vocab.TOPIC_HAND_INPUTS):
                run.hands[-1].append(decode(m))
            elif m.topic.endswith(vocab.TOPIC_LMI):
                u = decode(m)
                if int(u.seq) != INJECTED_SEQ:
                    run.updates.append(u)
            elif m.topic == vocab.TOPIC_DIAGNOSTICS:
                for st in decode(m).status:
                    d = run.diagnostics.setdefault(st.name, {})
                    for kv in st.values:
                        try:
                            v = float(kv.value)
                        except ValueError:
                            continue
                        if math.isfinite(v):
                            d[kv.key] = max(d.get(kv.key, -math.inf), v)
        run.truncated += bag.truncated


# -- analysis ---------------------------------------------------------------------------------
def hand_seqs(batches: list[Any]) -> list[int]:
    """The seqs of the hand input samples in the recorded ``HandInputs`` batches, in order,
    without the injector's."""
    return [int(s) for b in batches for s in b.seq if int(s) < INJECTED_SEQ]


def stamp(msg: Any) -> float:
    return float(msg.header.stamp.sec) + 1e-9 * float(msg.header.stamp.nanosec)


@dataclass
class Session:
    """The states of one device_driver process (seq restarts at 1), in seq order."""

    seqs: np.ndarray
    t: np.ndarray
    applied: np.ndarray
    status: np.ndarray
    twist: np.ndarray


def sessions(states: list[Any]) -> list[Session]:
    """Split the arrival-ordered states of one bag into device sessions (a new one where the
    seq goes backwards: a restarted device_driver), each sorted by seq."""
    groups: list[dict[int, Any]] = []
    last = math.inf
    for s in states:
        seq = int(s.seq)
        if seq == INJECTED_SEQ:
            continue           # the injector's malformed states, not the device's
        if seq < last:
            groups.append({})
        groups[-1][seq] = s
        last = seq
    out = []
    for g in groups:
        ks = sorted(g)
        out.append(Session(np.array(ks), np.array([stamp(g[k]) for k in ks]),
                           np.array([list(g[k].applied_wrench) for k in ks], dtype=float),
                           np.array([int(g[k].status) for k in ks]),
                           np.array([list(g[k].twist) for k in ks], dtype=float)))
    return out


def window(sess: list[Session], t0: float, t1: float) -> tuple[np.ndarray, np.ndarray,
                                                               np.ndarray]:
    """(t, applied, status) of the running (non-idle) states in [t0, t1], all sessions."""
    ts, us, st = [], [], []
    for s in sess:
        m = (s.t >= t0) & (s.t <= t1) & ((s.status & IDLE) == 0)
        ts.append(s.t[m])
        us.append(s.applied[m])
        st.append(s.status[m])
    return np.concatenate(ts), np.concatenate(us), np.concatenate(st)


def max_step(sess: list[Session], t0: float, t1: float) -> np.ndarray:
    """Largest per-cycle change of the applied wrench per axis between consecutive running
    states of one session in [t0, t1]."""
    best = np.zeros(3)
    for s in sess:
        m = np.flatnonzero((s.t >= t0) & (s.t <= t1) & ((s.status & IDLE) == 0))
        if m.size < 2:
            continue
        consecutive = np.diff(s.seqs[m]) == 1
        d = np.abs(np.diff(s.applied[m], axis=0))[consecutive]
        if d.size:
            best = np.maximum(best, d.max(axis=0))
    return best


RESYNC_RAMP = 0.2      # lmi_controller resync_ramp (config/haptic_topology.yaml)
STALE_AFTER = 0.05


def figures(run: FaultRun, name: str) -> dict[str, float]:
    """For fault ``name``, from its start to the next fault's (or the end of the run):

    * ``max_ratio``: largest |applied wrench| / limit over the axes (must stay <= 1);
    * ``recovery_s``: from the end of the fault (SIGCONT sent / process restarted) until the
      loop is back: ``watchdog``: the device applies the plain command again (fade-in done);
      ``ve_stop``, ``kill_ve_sim``: commands come from a fresh model again (the force then
      fades in over ``RESYNC_RAMP``); ``kill_lmi_controller``: the new controller answers
      from a fresh model; ``kill_device_driver``: the new driver runs the loop;
      ``kill_recorder``: from the kill to the second bag's first state (recording gap);
      the kills are measured from the kill (the process is started again at once), so
      they include the ~2-3 s a Python node needs to start on a loaded 2-core machine;
    * ``step_x``/``step_y``: largest per-cycle change of the applied wrench (N) after the
      fault's end, against ``base_x``/``base_y``: the same over the run's first second;
    * ``tail_s`` (kill_recorder): the kill time minus the first bag's last state.
    """
    names = list(run.events)
    t0, t1 = run.events[name]
    k = names.index(name)
    sess = [s for b in run.states for s in sessions(b)]
    end = (run.events[names[k + 1]][0] if k + 1 < len(names)
           else max(s.t[-1] for s in sess)) - 0.01
    t, u, st = window(sess, t0 - 0.01, end)
    cmds = [(stamp(c), float(c.update_age), int(c.mode)) for c in run.commands
            if int(c.state_seq) != INJECTED_SEQ]
    fresh = np.array(sorted(c[0] for c in cmds if c[1] < STALE_AFTER and c[2] != 2))
    fresh = fresh[fresh > t1]
    rec = math.nan
    out: dict[str, float] = {}
    if name == 'watchdog':
        ok = t[((st & WATCHDOG) == 0) & (t > t1)]
        rec = float(ok[0]) - t1 if ok.size else math.inf
    elif name in ('ve_stop', 'kill_ve_sim'):
        # The VE is current again: an update describing the loop less than STALE_AFTER ago
        # (its hand_input_seq + 1 was stamped less than that before the update); the
        # controller then fades the force in over RESYNC_RAMP.
        seq_t = {int(q): tt for s in sessions(run.states[0])[:1]
                 for q, tt in zip(s.seqs, s.t, strict=True)}
        start = t1 if name == 've_stop' else t0        # a kill restarts at once
        back = [stamp(u) for u in run.updates
                if start < stamp(u) < end and int(u.hand_input_seq) + 1 in seq_t
                and stamp(u) - seq_t[int(u.hand_input_seq) + 1] < STALE_AFTER]
        rec = min(back) - start if back else math.inf
    elif name == 'kill_lmi_controller':
        new_cmds = [c[0] for c in cmds if t0 + 0.5 < c[0] < end and c[2] != 2
                    and c[1] < STALE_AFTER]
        rec = min(new_cmds) - t0 if new_cmds else math.inf
    elif name == 'kill_device_driver':
        new = sessions(run.states[0])[-1]
        running = new.t[(new.status & IDLE) == 0]
        rec = float(running[0]) - t0 if running.size else math.inf
    elif name == 'kill_recorder':
        second = [stamp(s) for s in run.states[1]] if len(run.states) > 1 else []
        rec = (min(second) - t0) if second else math.inf
        first = [stamp(s) for s in run.states[0] if int(s.seq) != INJECTED_SEQ]
        out['tail_s'] = t0 - max(first)
    first_t = min(float(s.t[(s.status & IDLE) == 0][0]) for s in sess[:1])
    base = max_step(sess, first_t + 0.05, min(first_t + 1.0, run.events[names[0]][0] - 0.01))
    step = max_step(sess, t1, end)
    out.update({'max_ratio': float(np.max(np.abs(u) / LIMIT)) if u.size else math.nan,
                'recovery_s': rec, 'step_x': float(step[0]), 'step_y': float(step[1]),
                'base_x': float(base[0]), 'base_y': float(base[1]),
                'finite': float(np.all(np.isfinite(u)))})
    return out


def table(run: FaultRun) -> str:
    """The README's table of faults and measured results."""
    rows = ['| fault | max abs(applied) / limit | recovery [s] | max step per cycle x / y '
            '[N] (undisturbed: x / y) |', '|---|---|---|---|']
    for name in run.events:
        f = figures(run, name)
        rec = '-' if math.isnan(f['recovery_s']) else f'{f["recovery_s"]:.2f}'
        rows.append(f'| {name} | {f["max_ratio"]:.3f} | {rec} | {f["step_x"]:.3f} / '
                    f'{f["step_y"]:.3f} ({f["base_x"]:.3f} / {f["base_y"]:.3f}) |')
    return '\n'.join(rows)



def main() -> None:
    import tempfile

    from haptic_topology.nodes.dds_env import isolated_env

    out = Path(tempfile.mkdtemp(prefix='faults_'))
    domain = os.environ.get('ROS_DOMAIN_ID') or np.random.default_rng().integers(1, 100)
    os.environ.update(isolated_env(int(domain)))     # as the nodes do: DDS on this host
    run = run_faults(out)
    print(f'bags: {run.bags}; exit codes {run.exit_codes}; truncated {run.truncated}')
    print(f'states {len(run.states)} commands {len(run.commands)} hands {len(run.hands)}')
    for name, (a, b) in run.events.items():
        print(f'{name}: {a:.3f} .. {b:.3f} ({b - a:.3f} s)')
    print('| fault | max abs(applied) / limit | recovery [s] | max step per cycle x / y [N] '
          '(first second: x / y) |')
    print('|---|---|---|---|')
    for name in run.events:
        f = figures(run, name)
        print(f"| {name} | {f['max_ratio']:.3f} | {f['recovery_s']:.2f} | "
              f"{f['step_x']:.3f} / {f['step_y']:.3f} ({f['base_x']:.3f} / {f['base_y']:.3f}) |")
    missing = total = 0
    for bag in run.states:
        for sess in sessions(bag):
            d = np.diff(sess.seqs)
            missing += int(np.sum(d - 1))
            total += int(sess.seqs[-1] - sess.seqs[0] + 1)
    print(f'device states missing in the bags (best effort): {missing} of {total}')
    for key in ('device_driver: loop', 'lmi_controller: loop', 've_sim: loop'):
        rej = {k: int(v) for k, v in run.diagnostics.get(key, {}).items()
               if k.startswith(('rejected_', 'foreign_', 'controller_takeovers')) and v}
        print(f'{key} rejected: {rej}')
    print(f'injected: {run.injected}')



# -- per-fault figures ------------------------------------------------------------------------
LIMIT = np.array([20.0, 20.0, 2.0])     # circle.yaml device.wrench_limit


if __name__ == '__main__':
    main()
