"""The ROS 2 node graph in real processes: agreement with the offline simulation, a swapped
device backend, live parameters, malformed configuration.

Every test runs in the session's random ROS_DOMAIN_ID with discovery limited to this host
(``conftest.ros_domain_env``); every wait has a deadline.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import yaml
from offline_check import EXACT_COLUMNS, assert_equals_offline
from procs import stop_process

from haptic_topology.bag.graph_trace import GraphRun, read_graph_bag
from haptic_topology.bringup.run import run_graph
from haptic_topology.paths import config_dir
from haptic_topology.sim.scenario import load_scenario

pytestmark = pytest.mark.graph

TEST_DIR = Path(__file__).resolve().parents[1] / 'support'
PARAMS = config_dir() / 'haptic_topology.yaml'
#: Simulated seconds of each lock-step run: both of the runs' events are inside (the LMI's
#: constraint count changes at 0.82 s in fig6 and 0.85 s in fig8; fig8 with eq. 10 reaches
#: the workspace limit at 1.41 s).
DURATION = 1.5
#: Lock-step graphs of the module fixture that run at the same time.
CONCURRENT_RUNS = 4


def _graph_run(tmp_path: Path, scenario: str, mode: str, duration: float,
               backend: str | None = None, clock: str = 'lockstep',
               domain_id: int | None = None, layout: str = 'hosted') -> GraphRun:
    bag = tmp_path / f'{scenario}_{mode}_{clock}'
    codes = run_graph(scenario, mode, duration, bag, PARAMS, layout, backend=backend,
                      startup_timeout=60.0, clock=clock, domain_id=domain_id)
    assert all(c == 0 for c in codes.values()), codes
    return read_graph_bag(bag, scenario, load_scenario(scenario).linkage.dof)


LOCKSTEP_RUNS = (('fig6', 'penalty'), ('fig6', 'acceleration_only'), ('fig8', 'penalty'),
                 ('fig8', 'acceleration_only'), ('wall', 'penalty'))
#: Also in the pool: the spatial scenario (0.5 s) and the swapped backend (1 s).
SPATIAL, SPATIAL_DURATION = ('panda_link4', 'penalty'), 0.5
SWAPPED, SWAPPED_DURATION = ('fig8', 'fake_backend'), 1.0
#: The same in the separate-process layout and with the cycle in a loop thread of the driver
#: (the others run hosted with the loop process, the default).
SEPARATE_RUNS = (('fig6', 'penalty', 'separate'), ('fig8', 'acceleration_only', 'separate'),
                 ('wall', 'penalty', 'separate'), ('fig8', 'penalty', 'thread'),
                 ('wall', 'penalty', 'thread'))


@pytest.fixture(scope='module')
def lockstep_runs(tmp_path_factory: pytest.TempPathFactory,
                  spare_domains: list[int]) -> dict[tuple[str, ...], GraphRun]:
    """The lock-step runs, :data:`CONCURRENT_RUNS` at a time, each in a domain of its own:
    lock-step results do not depend on the machine's load, and the runs wait mostly on each
    other's messages. All ten at once (~30 node processes) beside the other pytest worker's
    graph tests starved every run past its deadline on 2 cores."""
    tmp = tmp_path_factory.mktemp('lockstep')
    jobs: dict[tuple[str, ...], tuple[str, str, float, str | None, str]] = {
        key: (key[0], key[1], DURATION, None, 'hosted') for key in LOCKSTEP_RUNS}
    jobs[SPATIAL] = (SPATIAL[0], 'penalty', SPATIAL_DURATION, None, 'hosted')
    jobs[SWAPPED] = ('fig8', 'penalty', SWAPPED_DURATION, 'fake_backend:CircleBackend',
                     'hosted')
    for key in SEPARATE_RUNS:
        jobs[key] = (key[0], key[1], DURATION, None, key[2])
    old_path = os.environ.get('PYTHONPATH')
    # The test double lives in test/support/: the node processes find it on PYTHONPATH.
    os.environ['PYTHONPATH'] = os.pathsep.join([str(TEST_DIR), *filter(None, [old_path])])
    for key in jobs:
        (tmp / '_'.join(key)).mkdir()
    try:
        with ThreadPoolExecutor(CONCURRENT_RUNS) as pool:
            futures = {key: pool.submit(_graph_run, tmp / '_'.join(key), sc, mode, duration,
                                        backend, domain_id=domain, layout=layout)
                       for (key, (sc, mode, duration, backend, layout)), domain
                       in zip(jobs.items(), spare_domains, strict=True)}
            return {key: f.result() for key, f in futures.items()}
    finally:
        if old_path is None:
            os.environ.pop('PYTHONPATH', None)
        else:
            os.environ['PYTHONPATH'] = old_path


#: Columns of a trace that the lock-step graph reproduces exactly (the VE's joint positions
#: and constraint counts are sampled at the updates in a bag, every cycle offline).
@pytest.mark.parametrize(('scenario', 'mode'), LOCKSTEP_RUNS)
def test_lockstep_graph_equals_offline_simulation(
        lockstep_runs: dict[tuple[str, ...], GraphRun], scenario: str, mode: str) -> None:
    """The lock-step graph (hosted layout: the device driver with the controller in its loop
    thread, the VE and the recorder, DDS between them) computes what ``simulate()``
    computes: device and VT poses equal to 1e-9 m at every cycle (bit-identical in practice:
    the same core objects, the same floating-point times), and the same drift summary."""
    run = lockstep_runs[(scenario, mode)]
    assert_equals_offline(run.trace, scenario, mode, DURATION)
    # Lock-step answers every state before the next, and the VE updates every update_period
    # device cycles of simulated time.
    sc = load_scenario(scenario)
    assert run.loop['max_consecutive_missed'] == 0
    assert run.loop['ve_update_rate_hz'] == pytest.approx(1.0 / (sc.update_period * sc.dt),
                                                          rel=1e-9)


@pytest.mark.parametrize('key', SEPARATE_RUNS, ids=lambda k: '-'.join(k))
def test_other_layouts_equal_hosted_layout_and_offline(
        lockstep_runs: dict[tuple[str, ...], GraphRun], key: tuple[str, str, str]) -> None:
    """The separate-process layout (state -> command over DDS) and the loop thread (the
    cycle in a thread of the driver's process instead of its loop process) compute in
    lock-step the same as the default hosted layout (the loop process) and ``simulate()``:
    every exact column bit for bit."""
    scenario, mode, _ = key
    separate, hosted = lockstep_runs[key].trace, lockstep_runs[(scenario, mode)].trace
    assert_equals_offline(separate, scenario, mode, DURATION)
    for col in EXACT_COLUMNS:
        np.testing.assert_array_equal(separate.columns[col], hosted.columns[col],
                                      err_msg=col)
    assert lockstep_runs[key].loop['max_consecutive_missed'] == 0


def test_lockstep_graph_equals_offline_simulation_spatial(
        lockstep_runs: dict[tuple[str, ...], GraphRun]) -> None:
    """The same agreement in 6-D: the Panda (config/robots/) held at a middle link
    (J_h 6 x 7, t >= 2), a 6-DOF device with an orientation stop, eq. 14, for 0.5 s."""
    graph = lockstep_runs[SPATIAL].trace
    assert graph.task_dim == 6
    assert_equals_offline(graph, SPATIAL[0], 'penalty', SPATIAL_DURATION)


def test_swapping_the_backend_needs_no_change_in_other_nodes(
        lockstep_runs: dict[tuple[str, ...], GraphRun]) -> None:
    """The test double (test/support/fake_backend.py) is selected by a parameter value only; in
    lock-step its states are exactly on its circle at t = k dt, and the loop around it ran
    unchanged (every state answered, the VE's hand reported at every cycle)."""
    sys.path.insert(0, str(TEST_DIR))
    from fake_backend import circle

    tr = lockstep_runs[SWAPPED].trace
    sc = load_scenario('fig8')
    from haptic_topology.dynamics import LinkageDynamics

    center = LinkageDynamics(sc.linkage).hand_pose(sc.q0) + sc.device_offset
    assert len(tr) == 1001
    expected = np.array([circle(center, 0.002, 1.0, t)[0] for t in tr.t])
    np.testing.assert_allclose(tr.columns['device_pose'], expected, rtol=0.0, atol=1e-12)
    assert np.all(np.isfinite(tr.columns['command']))
    assert np.all(np.isfinite(tr.columns['vt_pose']))
    assert np.nanmax(np.abs(tr.columns['command'])) > 0.0


# -- live parameters ------------------------------------------------------------------------
def _start_node(name: str, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, '-m', f'haptic_topology.nodes.{name}', '--ros-args', '--params-file',
         str(PARAMS), '-p', 'scenario:=fig6', *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)


@pytest.mark.parametrize('process', ['lmi_controller', 'device_driver'],
                         ids=['separate', 'hosted'])
def test_live_k_tc_takes_effect_and_bad_values_are_refused(process: str) -> None:
    """Live gains of ``lmi_controller``, in its own process or hosted by ``device_driver``
    (where the change is handed to the loop thread)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rcl_interfaces.msg import Parameter as ParamMsg
    from rcl_interfaces.msg import ParameterType, ParameterValue
    from rcl_interfaces.srv import GetParameters, SetParameters

    proc = _start_node(process)
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('param_test_client', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        def wait(future: rclpy.task.Future, timeout: float = 60.0) -> object:
            deadline = time.monotonic() + timeout
            while not future.done() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            assert future.done(), 'service call timed out'
            return future.result()

        set_cli = node.create_client(SetParameters, '/lmi_controller/set_parameters')
        get_cli = node.create_client(GetParameters, '/lmi_controller/get_parameters')
        assert set_cli.wait_for_service(timeout_sec=20.0), 'lmi_controller did not come up'

        def set_param(name: str, value: ParameterValue) -> object:
            req = SetParameters.Request(parameters=[ParamMsg(name=name, value=value)])
            return wait(set_cli.call_async(req)).results[0]  # type: ignore[attr-defined]

        def double(v: float) -> ParameterValue:
            return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=v)

        res = set_param('k_tc', double(55.0))
        assert res.successful, res.reason
        reports: list[str] = []
        node.create_subscription(
            DiagnosticArray, '/diagnostics',
            lambda m: reports.extend(kv.value for s in m.status
                                     if s.name == 'lmi_controller: loop'
                                     for kv in s.values if kv.key == 'k_tc'), 10)
        deadline = time.monotonic() + 10.0
        while '55.0' not in reports and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert '55.0' in reports, f'controller never reported k_tc = 55.0: {reports}'

        res = set_param('k_tc', double(-1.0))
        assert not res.successful
        assert 'k_tc' in res.reason and res.reason
        res = set_param('b_tc', double(float('nan')))
        assert not res.successful and 'b_tc' in res.reason
        res = set_param('mode', ParameterValue(type=ParameterType.PARAMETER_STRING,
                                               string_value='sideways'))
        assert not res.successful and 'mode' in res.reason
        res = set_param('scenario', ParameterValue(type=ParameterType.PARAMETER_STRING,
                                                   string_value='fig8'))
        assert not res.successful    # read-only
        got = wait(get_cli.call_async(GetParameters.Request(names=['k_tc'])))
        assert got.values[0].double_value == 55.0  # type: ignore[attr-defined]
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
        code, out = stop_process(proc, timeout=10)
    assert code == 0, out
    assert 'Traceback' not in out


# -- configuration errors -------------------------------------------------------------------
@pytest.mark.parametrize(('node', 'args', 'text'), [
    ('device_driver', ['-p', 'rate_hz:=5.0'], 'parameter rate_hz'),
    ('device_driver', ['-p', 'backend:=ros_topics'],
     'ros_topics: backend_options.pose_topic: expected a topic name (text), got None'),
    ('device_driver', ['-p', 'backend:=network', '-p', 'clock:=lockstep'],
     'backend network: the device runs on its own clock, so clock: lockstep cannot pace it'),
    ('lmi_controller', ['-p', 'scenario:=no_such_scenario'], 'no_such_scenario'),
    ('lmi_controller', ['-p', 'mode:=sideways'], 'parameter mode'),
    ('ve_sim', ['-p', 'update_period:=abc'], 'parameter update_period'),
])
def test_malformed_config_refuses_to_start_with_one_message(node: str, args: list[str],
                                                            text: str) -> None:
    proc = _start_node(node, *args)
    try:
        out, _ = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f'{node} did not refuse to start')
    text_out = out.decode(errors='replace')
    assert proc.returncode == 2, text_out
    assert 'Traceback' not in text_out
    assert f'{node}: error:' in text_out and text in text_out


def test_bad_params_file_refuses_to_start(tmp_path: Path) -> None:
    bad = tmp_path / 'bad.yaml'
    bad.write_text('device_driver:\n  ros__parameters:\n    rate_hz: [1, 2\n', encoding='utf-8')
    proc = subprocess.run(
        [sys.executable, '-m', 'haptic_topology.nodes.device_driver', '--ros-args',
         '--params-file', str(bad)], capture_output=True, timeout=30)
    out = (proc.stdout + proc.stderr).decode(errors='replace')
    assert proc.returncode == 2, out
    assert 'Traceback' not in out and 'device_driver: error:' in out


def test_run_command_composed(tmp_path: Path) -> None:
    """``haptic-topology run --composed``: one process, the device it started, bag, summary,
    loop figures."""
    bag = tmp_path / 'composed'
    proc = subprocess.run(
        [sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8', '--mode', 'penalty',
         '--duration', '1.0', '--composed', '--no-plot', '--out', str(bag)],
        capture_output=True, timeout=90)
    out = (proc.stdout + proc.stderr).decode(errors='replace')
    assert proc.returncode == 0, out
    assert 'final [mm]' in out and 'rtt p50 [ms]' in out
    assert '\ndevice: backend sim_maglev, sim_maglev planar\n' in out, out
    assert (bag / 'metadata.yaml').is_file() and (bag / 'trace.parquet').is_file()
    run = read_graph_bag(bag, 'fig8', 3)
    assert run.trace.t[-1] >= 0.9
    # ``analyze`` of the bag prints the loop table run printed: the same columns, in the
    # same order, and the same figures.
    done = subprocess.run(
        [sys.executable, '-m', 'haptic_topology.cli', 'analyze', str(bag), '--out',
         str(tmp_path / 'analysis'), '--no-plot'], capture_output=True, timeout=90)
    assert done.returncode == 0, done.stderr.decode(errors='replace')

    def loop_table(text: str, label: str) -> tuple[list[str], list[str]]:
        lines = text.split('\n')
        head = max(i for i, line in enumerate(lines)
                   if line.startswith('run ') and 'answered, device [%]' in line)
        row = next(line for line in lines[head:] if line.startswith(label))
        return [c.strip() for c in lines[head].split('  ') if c.strip()], \
            row[len(label):].split()

    assert loop_table(out, 'fig8 penalty') == loop_table(
        done.stdout.decode(errors='replace'), 'composed')


def test_run_of_a_contact_scenario_prints_and_draws_its_contacts(tmp_path: Path) -> None:
    """``haptic-topology run wall`` (lock-step): its drift table has the deepest penetration
    and the time in contact of its summary, and ``analyze``'s figure of its bag draws the
    wall, as the run's own plot does."""
    import matplotlib.pyplot as plt

    from haptic_topology.bag.analyze import load_run, run_figure

    bag = tmp_path / 'wall'
    proc = subprocess.run(
        [sys.executable, '-m', 'haptic_topology.cli', 'run', 'wall', '--clock', 'lockstep',
         '--duration', '0.5', '--no-plot', '--out', str(bag)], capture_output=True, timeout=120)
    out = proc.stdout.decode(errors='replace')
    assert proc.returncode == 0, out + proc.stderr.decode(errors='replace')
    summary = json.loads((bag / 'summary.json').read_text())
    assert summary['max_penetration_m'] > 0.0
    lines = out.split('\n')
    head = next(i for i, line in enumerate(lines) if line.startswith('scenario '))
    assert lines[head].endswith('max penetration [mm]  in contact [s]')
    assert lines[head + 2].split()[-2:] == [f'{summary["max_penetration_m"] * 1e3:.3f}',
                                            f'{summary["contact_time_s"]:.3f}']
    fig = run_figure(load_run(bag))
    try:
        labels = fig.axes[0].get_legend_handles_labels()[1]
        assert 'wall (half-plane)' in labels
    finally:
        plt.close(fig)


def test_run_command_with_a_scenario_file(tmp_path: Path) -> None:
    """``haptic-topology run FILE``: a scenario file of a name no built-in scenario has runs
    and is analysed against its own linkage; the summary has every process's CPU and
    resident set, and the loop's wake-up lateness."""
    doc = yaml.safe_load((config_dir() / 'scenarios' / 'fig8.yaml').read_text())
    doc['scenario']['name'] = 'my_fig8'
    scenario = tmp_path / 'mine.yaml'
    scenario.write_text(yaml.safe_dump(doc), encoding='utf-8')
    bag = tmp_path / 'bag'
    proc = subprocess.run(
        [sys.executable, '-m', 'haptic_topology.cli', 'run', str(scenario), '--mode',
         'penalty', '--duration', '1.0', '--composed', '--no-plot', '--out', str(bag)],
        capture_output=True, timeout=90)
    out = (proc.stdout + proc.stderr).decode(errors='replace')
    assert proc.returncode == 0, out
    summary = json.loads((bag / 'summary.json').read_text())
    assert summary['scenario'] == 'my_fig8'
    assert summary['rss_mb_composed'] > 0.0 and summary['cpu_composed'] > 0.0
    # The loop sleeps to absolute deadlines: how late it woke, never before a deadline.
    late = [summary[f'device_wake_late_{q}_ms'] for q in ('p50', 'p99', 'max')]
    assert 0.0 <= late[0] <= late[1] <= late[2], late
