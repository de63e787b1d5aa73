"""The recorder under load: what it stores of the graph's topics at ``factor`` times their rate.

Two processes besides this one, in a random ROS_DOMAIN_ID with discovery on this host only:

* ``recorder`` (``python -m haptic_topology.nodes.recorder --ros-args -p output:=<tmp>/bag
  -p nice:=0``), the node as the graph runs it (EventsExecutor, raw subscriptions, writer
  thread, zstd MCAP), at nice 0 like the publisher: this measures what the recorder can
  store. At its default nice (+10, so that it yields to the 1 kHz loop) it yields to the
  publisher too, which at 14x takes a whole core, and then it falls behind;
* a synthetic publisher (this file, ``--role publisher``) with the graph's topics and QoS, per
  1x: ``DeviceState``, ``DeviceCommand`` at 1 kHz, ``HandInputs`` (batches of 10 samples) and
  ``LmiUpdate`` at 100 Hz, ``/diagnostics`` at 3 Hz, with the sizes of the planar 3-DOF
  scenarios (every array field filled). Each message carries a sequence number running 1..N
  on its topic (``seq``; ``state_seq`` on DeviceCommand; a ``seq`` key in /diagnostics; the
  samples of the i-th HandInputs have seqs ``10 (i - 1) + 1 .. 10 i``). It wakes every
  1 ms and publishes on each topic what is due by then (``rate * factor * elapsed``), so at
  10x a tick is a burst of ~10 messages per topic; when it falls behind it catches up in a
  bigger burst, and at the deadline it stops without sending what is still due, so
  ``published_msgs_per_s`` is the rate it achieved (``publish_rate_fraction`` of nominal).

The publisher starts counting once every topic has a subscriber (the recorder) and discovery
had 0.5 s to complete both ways; it publishes for ``duration`` s and exits. The recorder then
gets up to 5 s to drain (until its CPU time stops growing), its ``/proc/<pid>/stat``
utime+stime is read, it is stopped with SIGINT, and the bag is read back with our reader.

Figures: per topic published, recorded, lost (published - recorded), whether the recorded
sequence numbers are exactly 1..N in order (``contiguous``), the first missing one and when it
was due (s into the run, at the nominal rate), the number of gaps and the longest; in total
the sustained msgs/s (recorded / duration), bag bytes (the .mcap files) and bytes/s, and
``cpu_fraction``: the recorder's user+system CPU seconds from the first published message
until just before SIGINT divided by that wall time (fraction of one core; includes the
drain). ``cpu_fraction_publisher`` is the same for the publisher over its publishing time.

Run: ``.venv/bin/python bench/recorder_load.py --duration 60 --factor 10`` (prints one JSON
object).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import IO, Any

from haptic_topology import vocabulary as vocab
from haptic_topology.processes import cpu_seconds, terminate

#: Topic (graph name) -> (message rate at 1x in Hz, field holding the sequence number).
TOPICS: dict[str, tuple[float, str]] = {
    vocab.TOPIC_STATE: (1000.0, 'seq'),
    vocab.TOPIC_COMMAND: (1000.0, 'state_seq'),
    vocab.TOPIC_HAND_INPUTS: (100.0, 'seq'),
    vocab.TOPIC_LMI: (100.0, 'seq'),
    vocab.TOPIC_DIAGNOSTICS: (3.0, 'seq'),
}
#: Samples per HandInputs message (one VE update period of the 1 kHz loop).
HAND_BATCH = 10
TICK_S = 1e-3
DISCOVERY_SETTLE_S = 0.5
DRAIN_MAX_S = 5.0
START_TIMEOUT_S = 40.0


# -- publisher process --------------------------------------------------------------------------
def _messages() -> dict[str, Any]:
    """One message per topic, every field of the planar 3-DOF graph filled."""
    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate

    v3 = [0.1, -0.2, 0.3]
    m33 = [1.0, 0.1, 0.0, 0.1, 1.0, 0.1, 0.0, 0.1, 1.0]
    state = DeviceState(task_dim=3, pose=v3, twist=v3, hand_wrench=v3, applied_wrench=v3,
                        status=0)
    state.header.frame_id = 'world'
    cmd = DeviceCommand(controller_id=1, mode=0, task_dim=3, wrench=v3, vt_pose=v3,
                        vt_twist=v3, constraint_count=0, update_age=0.004)
    cmd.header.frame_id = 'world'
    rows = v3 * HAND_BATCH
    hand = HandInputs(task_dim=3, seq=list(range(1, HAND_BATCH + 1)),
                      state_seq=list(range(1, HAND_BATCH + 1)),
                      stamp=[Time() for _ in range(HAND_BATCH)], pose=rows, twist=rows,
                      hand_wrench=rows, coupling_wrench=rows)
    hand.header.frame_id = 'world'
    upd = LmiUpdate(dof=3, task_dim=3, q=v3, dq=v3, mass_matrix=m33, gravity=v3,
                    hand_jacobian=m33, singular_values=v3, left_singular_vectors=m33,
                    constraint_count=1, constraint_weights=[1.0, 0.0, 0.0],
                    characteristic_length=0.12, hand_pose=v3, hand_twist=v3)
    upd.header.frame_id = 'world'
    diag = DiagnosticArray()
    status = DiagnosticStatus(level=bytes([0]), name='device_driver: loop', message='ok',
                              hardware_id='/device_driver')
    status.values = [KeyValue(key=k, value='0') for k in
                     ('seq', 'answered', 'rtt_p50_ms', 'rtt_p99_ms', 'period_p99_ms',
                      'cycles', 'stale', 'rejected')]
    diag.status = [status]
    return {vocab.TOPIC_STATE: state, vocab.TOPIC_COMMAND: cmd,
            vocab.TOPIC_HAND_INPUTS: hand, vocab.TOPIC_LMI: upd, vocab.TOPIC_DIAGNOSTICS: diag}


def _set_batch(msg: Any, i: int) -> None:
    """The i-th HandInputs: samples 10 (i - 1) + 1 .. 10 i."""
    msg.seq = msg.state_seq = list(range(HAND_BATCH * (i - 1) + 1, HAND_BATCH * i + 1))


def _publisher(duration: float, factor: float) -> int:
    """Publish every topic at ``factor`` x its rate for ``duration`` s; print JSON counts."""
    import rclpy

    from haptic_topology.nodes.qos import TOPIC_QOS

    rclpy.init()
    node = rclpy.create_node('recorder_load_publisher')
    msgs = _messages()
    pubs = {t: node.create_publisher(type(m), t, TOPIC_QOS[t]) for t, m in msgs.items()}
    deadline = time.monotonic() + START_TIMEOUT_S
    while any(p.get_subscription_count() < 1 for p in pubs.values()):
        if time.monotonic() > deadline:
            print('publisher: no subscriber', file=sys.stderr, flush=True)
            return 2
        time.sleep(0.02)
    time.sleep(DISCOVERY_SETTLE_S)  # the recorder's readers match our writers too

    order = list(msgs)
    rates = [TOPICS[t][0] * factor for t in order]
    sent = [0] * len(order)
    stamps = [msgs[t].header.stamp for t in order]
    diag_value = msgs[vocab.TOPIC_DIAGNOSTICS].status[0].values[0]
    setters: list[Any] = []
    for t in order:
        msg, field = msgs[t], TOPICS[t][1]
        if t == vocab.TOPIC_DIAGNOSTICS:
            setters.append(lambda i: setattr(diag_value, 'value', str(i)))
        elif t == vocab.TOPIC_HAND_INPUTS:
            setters.append(lambda i, m=msg: _set_batch(m, i))
        else:
            setters.append(lambda i, m=msg, f=field: setattr(m, f, i))
    publish = [pubs[t].publish for t in order]
    objs = [msgs[t] for t in order]
    print('publishing', flush=True)
    cpu0 = os.times()
    start = time.perf_counter()
    end = start + duration
    ticks = late_ticks = 0
    while True:
        now = time.perf_counter()
        if now >= end:  # what is still due is not sent: the rate reported is the achieved one
            break
        elapsed = now - start
        more = True
        while more:  # round robin over the topics until each has sent what is due
            more = False
            for k in range(len(order)):
                if sent[k] < int(elapsed * rates[k]):
                    i = sent[k] + 1
                    setters[k](i)
                    ns = time.time_ns()
                    stamps[k].sec, stamps[k].nanosec = divmod(ns, 1_000_000_000)
                    publish[k](objs[k])
                    sent[k] = i
                    more = True
        ticks += 1
        next_tick = start + ticks * TICK_S
        rem = next_tick - time.perf_counter()
        if rem > 0:
            time.sleep(rem)
        else:
            late_ticks += 1
    wall = time.perf_counter() - start
    cpu1 = os.times()
    print(json.dumps({'published': dict(zip(order, sent, strict=True)), 'wall_s': wall,
                      'late_ticks': late_ticks, 'ticks': ticks,
                      'cpu_fraction': (cpu1.user - cpu0.user + cpu1.system - cpu0.system)
                      / wall}), flush=True)
    time.sleep(0.2)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


# -- orchestration ------------------------------------------------------------------------------
def _cpu_seconds(pid: int) -> float:
    """utime + stime of process ``pid`` (all its threads) in seconds (it must be running)."""
    cpu = cpu_seconds(pid)
    if cpu is None:
        raise RuntimeError(f'process {pid} is gone')
    return cpu


class _Lines:
    """Collects a process's output lines in a thread; waits for a line holding a mark."""

    def __init__(self, stream: IO[str]) -> None:
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._done = False
        threading.Thread(target=self._pump, args=(stream,), daemon=True).start()

    def _pump(self, stream: IO[str]) -> None:
        for line in stream:
            with self._cond:
                self.lines.append(line.rstrip('\n'))
                self._cond.notify_all()
        with self._cond:
            self._done = True
            self._cond.notify_all()

    def wait_for(self, mark: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not any(mark in ln for ln in self.lines):
                left = deadline - time.monotonic()
                if self._done or left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def text(self) -> str:
        with self._cond:
            return '\n'.join(self.lines)


def _env() -> dict[str, str]:
    from haptic_topology.nodes.dds_env import isolated_env

    return isolated_env(random.SystemRandom().randint(1, 100),
                        dict(os.environ, PYTHONUNBUFFERED='1'))


def _stop(proc: subprocess.Popen[str]) -> None:
    """SIGINT, then SIGTERM, then SIGKILL, each after a timeout."""
    terminate(proc, 30.0, 10.0)


def _wait_idle(pid: int, max_s: float) -> float:
    """Wait until process ``pid`` uses < 5 % of a core over 0.2 s (at most ``max_s``);
    return the time waited."""
    t0 = time.monotonic()
    last = _cpu_seconds(pid)
    while time.monotonic() - t0 < max_s:
        time.sleep(0.2)
        cpu = _cpu_seconds(pid)
        if cpu - last < 0.01:
            break
        last = cpu
    return time.monotonic() - t0


def _read_bag(path: Path) -> tuple[dict[str, list[int]], int, bool]:
    """Sequence numbers per graph topic in file order, .mcap bytes, truncated?"""
    from haptic_topology.bag.reader import decoder, iter_messages, open_bag

    bag = open_bag(path)
    decode = decoder()
    seqs: dict[str, list[int]] = {t: [] for t in TOPICS}
    for msg in iter_messages(bag):
        topic = msg.topic.lstrip('/') if msg.topic != vocab.TOPIC_DIAGNOSTICS else msg.topic
        if topic not in seqs:
            continue
        obj = decode(msg)
        if topic == vocab.TOPIC_DIAGNOSTICS:
            # The synthetic publisher's status only (the recorder reports on the same topic).
            kv = {v.key: v.value for v in obj.status[0].values}
            if 'seq' in kv and obj.status[0].name == 'device_driver: loop':
                seqs[topic].append(int(kv['seq']))
        elif topic == vocab.TOPIC_HAND_INPUTS:
            seqs[topic].append(int(obj.seq[-1]) // HAND_BATCH)     # message number
        else:
            seqs[topic].append(int(getattr(obj, TOPICS[topic][1])))
    return seqs, bag.size, bool(bag.truncated)


def _gaps(missing: list[int]) -> list[tuple[int, int]]:
    """Runs of consecutive numbers in the sorted ``missing``: (first, length)."""
    runs: list[tuple[int, int]] = []
    for n in missing:
        if runs and runs[-1][0] + runs[-1][1] == n:
            runs[-1] = (runs[-1][0], runs[-1][1] + 1)
        else:
            runs.append((n, 1))
    return runs


def _topic_figures(published: int, got: list[int], duration: float,
                   rate: float) -> dict[str, Any]:
    wanted = set(range(1, published + 1))
    seen = set(got)
    missing = sorted(wanted - seen)
    gaps = _gaps(missing)
    return {
        'published': published,
        'recorded': len(got),
        'lost': published - len(got),
        'contiguous': got == list(range(1, published + 1)),
        'first_missing_seq': missing[0] if missing else None,
        'first_loss_at_s': (missing[0] - 1) / rate if missing else None,
        'missing': len(missing),
        'gaps': len(gaps),
        'longest_gap': max((n for _, n in gaps), default=0),
        'duplicates': len(got) - len(seen),
        'unexpected': len(seen - wanted),
        'published_per_s': published / duration,
        'recorded_per_s': len(got) / duration,
    }


def run(duration: float = 60.0, factor: float = 1.0) -> dict[str, Any]:
    """Run recorder and publisher for ``duration`` s at ``factor`` x the graph's rates;
    return the figures (see module doc)."""
    env = _env()
    with tempfile.TemporaryDirectory(prefix='recorder_load_') as tmp:
        bag = Path(tmp) / 'bag'
        rec = subprocess.Popen(
            [sys.executable, '-m', 'haptic_topology.nodes.recorder', '--ros-args', '-p',
             f'output:={bag}', '-p', 'nice:=0'],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
            start_new_session=True)
        pub: subprocess.Popen[str] | None = None
        try:
            assert rec.stdout is not None
            rec_out = _Lines(rec.stdout)
            if not rec_out.wait_for('recording to', START_TIMEOUT_S):
                raise RuntimeError(f'recorder did not start:\n{rec_out.text()}')
            pub = subprocess.Popen(
                [sys.executable, __file__, '--role', 'publisher', '--duration', str(duration),
                 '--factor', str(factor)],
                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                start_new_session=True)
            assert pub.stdout is not None
            pub_out = _Lines(pub.stdout)
            if not pub_out.wait_for('publishing', START_TIMEOUT_S + 5.0):
                raise RuntimeError(f'publisher did not start:\n{pub_out.text()}')
            t0 = time.monotonic()
            cpu0 = _cpu_seconds(rec.pid)
            pub.wait(timeout=duration + 30.0)
            drain_s = _wait_idle(rec.pid, DRAIN_MAX_S)
            cpu1 = _cpu_seconds(rec.pid)
            wall = time.monotonic() - t0
            _stop(rec)
            pub_out.wait_for('"published"', 5.0)
            stats = next((json.loads(ln) for ln in pub_out.lines if '"published"' in ln), None)
            if pub.returncode != 0 or stats is None:
                raise RuntimeError(f'publisher failed ({pub.returncode}):\n{pub_out.text()}')
            if rec.returncode != 0:
                raise RuntimeError(f'recorder exited with {rec.returncode}:\n{rec_out.text()}')
        finally:
            for proc in (pub, rec):
                if proc is not None:
                    _stop(proc)
        seqs, size, truncated = _read_bag(bag)
    pub_wall = float(stats['wall_s'])
    per_topic = {t: _topic_figures(int(stats['published'][t]), seqs[t], pub_wall,
                                   TOPICS[t][0] * factor) for t in TOPICS}
    published = sum(f['published'] for f in per_topic.values())
    recorded = sum(f['recorded'] for f in per_topic.values())
    nominal = sum(r for r, _ in TOPICS.values()) * factor
    summary = next((ln for ln in rec_out.lines if ln.startswith('bag written')), '')
    return {
        'factor': factor,
        'duration_s': pub_wall,
        'nominal_msgs_per_s': nominal,
        'published_msgs_per_s': published / pub_wall,
        'publish_rate_fraction': published / pub_wall / nominal,
        'recorded_msgs_per_s': recorded / pub_wall,
        'published': published,
        'recorded': recorded,
        'lost': published - recorded,
        'lossless': all(f['contiguous'] for f in per_topic.values()) and not truncated,
        'cpu_fraction': (cpu1 - cpu0) / wall,
        'cpu_window_s': wall,
        'drain_s': drain_s,
        'cpu_fraction_publisher': stats['cpu_fraction'],
        'publisher_late_ticks': stats['late_ticks'],
        'bag_bytes': size,
        'bytes_per_s': size / pub_wall,
        'bag_truncated': truncated,
        'recorder_summary': summary,
        'per_topic': per_topic,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    ap.add_argument('--role', choices=('bench', 'publisher'), default='bench',
                    help=argparse.SUPPRESS)
    ap.add_argument('--duration', type=float, default=60.0, help='publishing time (s)')
    ap.add_argument('--factor', type=float, default=1.0,
                    help='multiple of the graph rates (1: 2 x 1 kHz + 2 x 100 Hz + 3 Hz)')
    a = ap.parse_args()
    if a.duration <= 0 or a.factor <= 0:
        ap.error('--duration and --factor must be > 0')
    if a.role == 'publisher':
        raise SystemExit(_publisher(a.duration, a.factor))
    print(json.dumps(run(a.duration, a.factor), indent=2))


if __name__ == '__main__':
    main()
