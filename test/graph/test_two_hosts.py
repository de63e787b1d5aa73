"""The VE on another host (``scripts/two_hosts.sh``, ``haptic_topology.net.delay_bridge``).

The delay line's draws, settings and counters are checked everywhere. The graph test needs
root and network namespaces: it runs fig8 for 2 s with ``ve_sim`` in one namespace and the
rest in another, 5 ms one-way delay (+-20 % jitter, 1 % loss) between them, and asserts only
what holds on any machine: the run finished, the VE's updates crossed the link into the bag,
every applied wrench is finite and within the device's limit, the link stage forwarded
frames both ways with the delays it drew (each frame left no earlier than drawn), and no
namespace is left behind. No timing thresholds: the drift against delay is a measurement
(``bench/two_hosts_delay.py``). Elsewhere it is skipped with the reason.
"""

from __future__ import annotations

import doctest
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from haptic_topology.bringup.options import node_prefixes
from haptic_topology.bringup.partition import descendants
from haptic_topology.device.loop_process import CHILD_MODULE
from haptic_topology.errors import ConfigError
from haptic_topology.net import delay_bridge
from haptic_topology.net.delay_bridge import DelayLine, DirectionStats, LinkSettings, figures
from haptic_topology.processes import STACKS_SIGNAL, cmdline

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / 'scripts' / 'two_hosts.sh'
#: The processes that write their stacks on STACKS_SIGNAL once started (others die of it).
STACK_DUMPERS = ('bin/haptic-topology', 'haptic_topology.nodes.', CHILD_MODULE)


# -- the delay line (no privileges) ---------------------------------------------------------
def test_docstring_examples() -> None:
    assert doctest.testmod(delay_bridge, raise_on_error=True).attempted >= 2


def test_delays_are_uniform_within_the_jitter_and_the_loss_is_seeded() -> None:
    s = LinkSettings(delay=0.020, jitter=0.2, loss=0.01, seed=7)
    line = DelayLine(s)
    draws = [line.draw() for _ in range(20000)]
    kept = np.array([d for d in draws if d is not None])
    lost = len(draws) - kept.size
    assert 0.016 <= kept.min() and kept.max() <= 0.024
    assert abs(kept.mean() - 0.020) < 0.0002            # uniform: mean d (20000 draws)
    assert 120 <= lost <= 280                            # 1 %: 200 expected, binomial 5 sigma
    again = DelayLine(s)
    assert [again.draw() for _ in range(20000)] == draws  # same seed, same fates


def test_no_delay_and_no_loss_pass_frames_through_at_once() -> None:
    line = DelayLine(LinkSettings(delay=0.0, jitter=0.2, loss=0.0))
    assert {line.draw() for _ in range(100)} == {0.0}


@pytest.mark.parametrize(('delay', 'jitter', 'loss', 'text'), [
    (-0.001, 0.2, 0.01, 'delay must be in [0, 10] s, got -0.001'),
    (float('nan'), 0.2, 0.01, 'delay must be in [0, 10] s, got nan'),
    (0.005, 1.0, 0.01, 'jitter must be a fraction in [0, 1), got 1.0'),
    (0.005, 0.2, 1.5, 'loss must be a probability in [0, 1), got 1.5'),
])
def test_bad_link_settings_are_refused(delay: float, jitter: float, loss: float,
                                       text: str) -> None:
    with pytest.raises(ConfigError) as err:
        LinkSettings(delay, jitter, loss)
    assert str(err.value) == text


def test_counters_count_overtaken_frames_and_achieved_delays() -> None:
    st = DirectionStats()
    st.sent(arrival=1.000, drawn=0.005, now=1.006)
    st.sent(arrival=0.999, drawn=0.006, now=1.0061)     # arrived earlier, sent later
    st.sent(arrival=1.001, drawn=0.005, now=1.0065)
    d = st.to_dict()
    assert (d['forwarded'], d['overtaken']) == (3, 1)
    assert d['drawn_delay_ms']['max'] == 6.0
    assert d['achieved_delay_ms']['max'] == pytest.approx(7.1)
    assert figures([]) == dict.fromkeys(('mean', 'min', 'p50', 'p99', 'max'))


def test_bridge_without_the_interface_says_so() -> None:
    name = 'htnone' + secrets.token_hex(2)
    done = subprocess.run([sys.executable, '-m',
                           'haptic_topology.net.delay_bridge', '--a', name, '--b', name,
                           '--delay-ms', '5'], capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 2
    assert done.stderr.strip() == (f"delay_bridge: error: interface '{name}': no such "
                                   'interface in this network namespace')


def test_node_prefix_option() -> None:
    assert node_prefixes(['ve_sim=ip netns exec ht_ve'], 'hosted') == {
        've_sim': ['ip', 'netns', 'exec', 'ht_ve']}
    with pytest.raises(ConfigError) as err:
        node_prefixes(['lmi_controller=ip netns exec x'], 'hosted')
    assert str(err.value) == ("--node-prefix: expected NODE=COMMAND with NODE one of recorder, "
                              "ve_sim, device_driver, got 'lmi_controller=ip netns exec x'")
    with pytest.raises(ConfigError):
        node_prefixes(['ve_sim='], 'hosted')


# -- the graph across namespaces (root) ------------------------------------------------------
def _why_not() -> str | None:
    if shutil.which('ip') is None:
        return "no 'ip' command"
    done = subprocess.run(['bash', str(SCRIPT), 'check'], capture_output=True, text=True)
    return None if done.returncode == 0 else done.stdout.strip() or done.stderr.strip()


def _namespaces() -> set[str]:
    out = subprocess.run(['ip', 'netns', 'list'], capture_output=True, text=True).stdout
    return {line.split()[0] for line in out.splitlines() if line.strip()}


def _script(args: list[str], env: dict[str, str], bag: Path,
            timeout: float = 200.0) -> subprocess.CompletedProcess[str]:
    """``two_hosts.sh ARGS`` in a session of its own, its output kept in ``bag``'s
    directory. Past ``timeout`` s the test fails with what there is to know of where it
    hung: every thread's stack of the ``haptic-topology`` commands, nodes and loop process
    it started (SIGUSR1; the device server in its own session too), then, after a Ctrl-C to
    the script's process group (the script takes its namespaces down, ``run`` stops the
    nodes and copies their logs into the bag), its output and the end of each node's log."""
    out_path = bag.parent / f'{bag.name}.out'
    env = dict(env, PYTHONUNBUFFERED='1')
    with out_path.open('wb') as out:
        p = subprocess.Popen(['bash', str(SCRIPT), *args], env=env, cwd=REPO, stdout=out,
                             stderr=subprocess.STDOUT, start_new_session=True)
    try:
        code = p.wait(timeout)
    except subprocess.TimeoutExpired:
        for pid in descendants(p.pid):
            if (any(m in ' '.join(cmdline(pid)) for m in STACK_DUMPERS)
                    and _catches(pid, STACKS_SIGNAL)):      # not one still starting up
                os.kill(pid, STACKS_SIGNAL)
        time.sleep(2.0)
        os.killpg(p.pid, signal.SIGINT)
        try:
            p.wait(60.0)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        logs = ''.join(f'\n--- {f.name} (end) ---\n' + f.read_text(errors='replace')[-4000:]
                       for f in sorted((bag / 'logs').glob('*.log')))
        pytest.fail(f'two_hosts.sh {" ".join(args)}: not done within {timeout:g} s; its '
                    f'output:\n{out_path.read_text(errors="replace")[-6000:]}{logs}')
    return subprocess.CompletedProcess(p.args, code, out_path.read_text(errors='replace'), '')


def _catches(pid: int, sig: int) -> bool:
    """Whether process ``pid`` has a handler for ``sig`` (``SigCgt`` of its status)."""
    try:
        status = Path(f'/proc/{pid}/status').read_text()
    except OSError:
        return False
    mask = next((int(line.split()[1], 16) for line in status.splitlines()
                 if line.startswith('SigCgt:')), 0)
    return bool(mask >> (sig - 1) & 1)


@pytest.fixture
def prefix(tmp_path: Path) -> Iterator[str]:
    """Namespace prefix unique to this test; whatever it leaves is torn down afterwards."""
    reason = _why_not()
    if reason:
        pytest.skip(reason)
    p = f'htt{secrets.token_hex(3)}_'
    yield p
    subprocess.run(['bash', str(SCRIPT), 'down'], capture_output=True,
                   env=dict(os.environ, HT_PREFIX=p, HT_STATE=str(tmp_path / 'state')))


@pytest.mark.graph
@pytest.mark.timeout(300)      # 200 s for the script, then its stacks and logs
def test_ve_in_another_namespace_behind_a_delayed_link(prefix: str, tmp_path: Path) -> None:
    from haptic_topology.bag.reader import iter_messages, open_bag
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.sim.trace_io import read_trace

    bag = tmp_path / 'bag'
    env = dict(os.environ, HT_PREFIX=prefix, HT_STATE=str(tmp_path / 'state'), OUT=str(bag))
    done = _script(['run', 'fig8', '5', '--duration', '2', '--no-plot'], env, bag)
    assert not {ns for ns in _namespaces() if ns.startswith(prefix)}, 'namespaces left'
    assert done.returncode == 0, done.stdout[-6000:]

    # The graph ran, and the VE's updates crossed the link into the recorder's bag.
    summary = json.loads((bag / 'summary.json').read_text())
    assert summary['samples'] > 0
    updates = sum(1 for m in iter_messages(open_bag(bag)) if m.topic.endswith('lmi/update'))
    assert updates > 0

    # Every applied wrench finite and within the device's limit.
    trace = read_trace(bag / 'trace.parquet')
    applied = trace.columns['applied']
    limit = np.asarray(load_scenario('fig8').device.wrench_limit)
    assert np.all(np.isfinite(applied))
    assert np.all(np.abs(applied) <= limit + 1e-9)

    # The link stage's own counters.
    link = json.loads((bag / 'link.json').read_text())
    if link['stage'] == 'delay_bridge':
        assert link['state'] == 'stopped'
        for d in link['directions'].values():      # both ways: lab -> VE and VE -> lab
            assert d['forwarded'] > 0
            assert d['received'] == (d['forwarded'] + d['dropped'] + d['send_errors']
                                     + d['truncated'] + d['pending'])
            drawn, achieved = d['drawn_delay_ms'], d['achieved_delay_ms']
            assert 4.0 <= drawn['min'] and drawn['max'] <= 6.0    # 5 ms +-20 %
            assert achieved['min'] >= drawn['min'] - 1e-3         # none left before its time
    else:
        assert link['stage'] == 'netem' and link['delay_ms'] == 5


@pytest.mark.graph
@pytest.mark.timeout(300)      # 200 s for the script, then its stacks and logs
def test_device_server_in_another_namespace_behind_a_lossy_link(prefix: str,
                                                                tmp_path: Path) -> None:
    """The network backend across the namespace pair (issue 15, item 2): the device server in
    the far namespace behind 1 ms +-20 % with 1 % frame loss, the graph in the near one, the
    link authenticated with a key, and a forger on the link (issue 60) that sees every
    command and sends forged ones with the driver's session and next seq, and replays: the
    device applied none of them."""
    from network_harness import read_log

    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.sim.trace_io import read_trace

    bag = tmp_path / 'bag'
    env = dict(os.environ, HT_PREFIX=prefix, HT_STATE=str(tmp_path / 'state'), OUT=str(bag),
               HT_LOSS='0.01', HT_FORGER='1')
    done = _script(['run-device', 'fig8', '1', '--duration', '2', '--no-plot'], env, bag)
    assert not {ns for ns in _namespaces() if ns.startswith(prefix)}, 'namespaces left'
    assert done.returncode == 0, done.stdout[-6000:]

    # The loop ran through the remote device; what it applied is finite and within limits.
    assert json.loads((bag / 'summary.json').read_text())['samples'] > 0
    trace = read_trace(bag / 'trace.parquet')
    applied = trace.columns['applied']
    limit = np.asarray(load_scenario('fig8').device.wrench_limit)
    assert np.all(np.isfinite(applied))
    assert np.all(np.abs(applied) <= limit + 1e-9)

    # The server took the driver's commands across the link, none of them malformed, and
    # answered with states; two client sessions: the run's preflight (released) and the run.
    server = json.loads((bag / 'device_server.json').read_text())
    assert server['commands'] > 0 and server['states_sent'] > 0
    assert server['malformed'] == 0 and server['client_sessions'] == 2

    # The forger saw the commands and sent its forgeries; the device refused each kind
    # (at most what was sent: the link loses some) and never applied the forged wrench.
    assert server['authenticated'] == 1
    assert 'link authenticated (BLAKE2b-128' in (bag / 'device_server.log').read_text()
    forger = json.loads((bag / 'forger.json').read_text())
    sent = forger['sent']
    assert forger['seen'] > 0 and min(sent.values()) > 0, forger
    for reason, kind in (('unauthenticated', 'unauthenticated'), ('wrong_key', 'own_key'),
                         ('mac', 'tampered')):
        assert 1 <= server[f'rejected_{reason}'] <= sent[kind], (reason, server, sent)
    _, _, seq, u, _ = read_log(bag / 'device_server_log.csv')
    assert np.count_nonzero(seq) > 0
    assert not np.any(np.all(np.isclose(u, forger['wrench']), axis=1))

    link = json.loads((bag / 'link.json').read_text())
    if link['stage'] == 'delay_bridge':
        for d in link['directions'].values():      # commands one way, states the other
            assert d['forwarded'] > 0
            drawn = d['drawn_delay_ms']
            assert 0.8 <= drawn['min'] and drawn['max'] <= 1.2    # 1 ms +-20 %
    else:
        assert link['stage'] == 'netem' and link['delay_ms'] == 1


def test_without_root_every_command_is_skipped_in_one_line(
        tmp_path: Path, request: pytest.FixtureRequest) -> None:
    if os.geteuid() != 0:
        argv = ['bash', str(SCRIPT), 'up', '5']
    elif shutil.which('setpriv'):
        # The checkout may sit in a directory only root can enter (a clone under mktemp -d):
        # the unprivileged user runs a copy of the script from a directory it can read.
        readable = Path(tempfile.mkdtemp(prefix='ht_two_hosts_'))
        readable.chmod(0o755)
        request.addfinalizer(lambda: shutil.rmtree(readable, ignore_errors=True))
        script = readable / 'two_hosts.sh'
        shutil.copy(SCRIPT, script)
        script.chmod(0o644)
        argv = ['setpriv', '--reuid=65534', '--regid=65534', '--clear-groups',
                'bash', str(script), 'up', '5']
    else:
        pytest.skip('root without setpriv: cannot drop privileges to try')
    done = subprocess.run(argv, capture_output=True, text=True, cwd='/',
                          env=dict(os.environ, HT_STATE=str(tmp_path / 'state')))
    assert done.returncode == 0
    assert done.stdout.strip().splitlines() == [
        'two_hosts.sh: skipped: needs root (ip netns, veth, packet sockets); run it with sudo']
