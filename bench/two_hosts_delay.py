"""The VE on another host: drift against the one-way delay of the link (issue 15, item 3).

For each scenario (default fig8 and circle) and one-way delay (default 0, 5, 20, 50 ms, each
with +-20 % uniform jitter and 1 % frame loss), runs ``scripts/two_hosts.sh run``: ``ve_sim``
in one network namespace, ``device_driver`` (hosting ``lmi_controller``) and the recorder in
another, DDS between them through the link stage (netem where the kernel has it, else
``haptic_topology.net.delay_bridge``). One run at a time. Then, per run:

* drift (device - VT grasp point in the VE): final / max / RMS, from the run's
  ``summary.json``, and the same figures of ``haptic-topology simulate`` of the scenario for
  the same duration (the offline run);
* the live device path against the offline one: max and RMS distance between the device
  positions at the same time since engagement (offline interpolated);
* the re-sync: model age when an update arrives (arrival of the first ``LmiUpdate`` that
  consumed the hand input of state s minus arrival of state s, both in the recorder: about
  the number of inputs the LMI replays, in ms), the
  longest gap between updates, the controller's degradations and held re-syncs (its last
  ``/diagnostics`` in the bag);
* loop figures (answered %, period p99) and the link stage's counters (frames forwarded and
  dropped, delay achieved).

Prints a Markdown table, writes ``results.json`` into the output directory and plots drift
against delay into ``docs/img/two_hosts_delay.png``.

Run from the repository root, as root (network namespaces)::

    python bench/two_hosts_delay.py [--scenarios fig8 circle] [--delays 0 5 20 50]
        [--circle-duration 10] [--profiles loopback two_hosts default] [--out bags/two_hosts]
        [--plot docs/img/two_hosts_delay.png] [--reuse] [--repeats OTHER/results.json]

``--remote-device`` (issue 15, item 3, "what a remote device costs"): the device on the far
side of the link instead of the VE. Same as ``--profiles loopback device_loopback device
--delays 1 --losses 0 0.01`` (unless given) and no plot unless ``--plot``: ``loopback`` =
``sim_maglev`` in the driver (the baseline), ``device_loopback`` = ``haptic-topology
device-server`` on this host's loopback and ``backend: network`` (no namespaces, no link),
``device`` = ``scripts/two_hosts.sh run-device`` (the server in the far namespace behind the
link, the whole graph in the near one). Per run also: FAULT and WATCHDOG states in the bag,
the driver's fault onsets / cycles (its last ``/diagnostics``), the server's counters
(command timeouts and cycles at zero, lost / late commands, missed deadlines, CPU) and the
frames the link dropped per direction. One repetition per output directory: ``--out``
another directory for a second one.

The table and plot of docs/results.md: ``--profiles loopback two_hosts default``, then ``--profiles
two_hosts --out bags/two_hosts_rep2 --plot /tmp/rep2.png``, then ``--reuse --profiles
loopback two_hosts default --repeats bags/two_hosts_rep2/results.json`` (redraws the plot).

``--profiles`` (default ``loopback two_hosts``): ``loopback`` = the baseline, one
``haptic-topology run`` per scenario with every node on this host (no namespaces, no link);
the others are the Fast DDS setup of both sides (``scripts/two_hosts.sh``
``HT_DDS_PROFILE``): ``two_hosts`` = ``config/fastdds_two_hosts.xml`` (UDP only, reliable
heartbeat 20 ms), ``default`` = Fast DDS's defaults over UDP. ``--reuse`` analyses the
bags already in the output directory instead of running. Without root it prints one line
and exits 0.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology import vocabulary as vocab
from haptic_topology.processes import process_times

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / 'scripts' / 'two_hosts.sh'
CONTROLLER_STATUS = 'lmi_controller: loop'


#: The link's frame loss unless ``--losses`` says otherwise (bag names carry any other).
DEFAULT_LOSS = 0.01
#: Profiles whose device is ``haptic-topology device-server`` (``--remote-device``).
DEVICE_PROFILES = ('device_loopback', 'device')
DRIVER_STATUS = 'device_driver: loop'


def bag_name(profile: str, scenario: str, delay: float | None,
             loss: float = DEFAULT_LOSS) -> str:
    if delay is None:
        return f'{profile}_{scenario}'
    tail = '' if loss == DEFAULT_LOSS else f'_loss{loss * 100:g}'
    return f'{profile}_{scenario}_{delay:g}ms{tail}'


def network_params(path: Path, host: str, port: int) -> None:
    """config/haptic_topology.yaml with device_driver's ``backend: network`` at host:port."""
    import yaml

    params = yaml.safe_load((REPO / 'config' / 'haptic_topology.yaml').read_text('utf-8'))
    drv = params['device_driver']['ros__parameters']
    drv['backend'] = 'network'
    drv['backend_options'] = f'{{host: {host}, port: {port}}}'
    path.write_text(yaml.safe_dump(params, sort_keys=False), encoding='utf-8')


def run_device_loopback(scenario: str, duration: float, bag: Path) -> None:
    """``haptic-topology device-server`` on this host's loopback, the graph with ``backend:
    network`` pointed at it (no namespaces, no link); the server's files go into the bag."""
    import shutil
    import tempfile
    import time

    exe = str(REPO / '.venv' / 'bin' / 'haptic-topology')
    with tempfile.TemporaryDirectory(prefix='ht_device_') as tmp:
        d = Path(tmp)
        ready, summary, log = d / 'ready.json', d / 'device_server.json', d / 'device_server.log'
        srv_argv = [exe, 'device-server', '--scenario', scenario, '--port', '0',
                    '--ready-file', str(ready), '--summary', str(summary)]
        print(f'$ {" ".join(srv_argv)} &', flush=True)
        with open(log, 'wb') as out:
            srv = subprocess.Popen(srv_argv, cwd=REPO, stdout=out, stderr=subprocess.STDOUT)
        try:
            end = time.monotonic() + 30.0
            while not ready.is_file():
                if srv.poll() is not None or time.monotonic() > end:
                    raise RuntimeError(f'device-server did not serve: {log.read_text()[-2000:]}')
                time.sleep(0.1)
            port = json.loads(ready.read_text(encoding='utf-8'))['port']
            network_params(d / 'params.yaml', '127.0.0.1', port)
            argv = [exe, 'run', scenario, '--duration', f'{duration:g}', '--no-plot', '--out',
                    str(bag), '--params', str(d / 'params.yaml')]
            print(f'$ {" ".join(argv)}', flush=True)
            done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True)
            cpu = process_times(srv.pid)
        finally:
            srv.send_signal(2)      # SIGINT: the server writes its summary
            try:
                srv.wait(10)
            except subprocess.TimeoutExpired:
                srv.kill()
                srv.wait()
        if done.returncode != 0:
            raise RuntimeError(f'{scenario} device loopback failed ({done.returncode}):\n'
                               f'{done.stdout[-2000:]}\n{done.stderr[-2000:]}')
        for f in (summary, log):
            if f.is_file():
                shutil.copy(f, bag / f.name)
        if cpu is not None:
            (bag / 'device_server_cpu.json').write_text(json.dumps(cpu) + '\n', 'utf-8')


def run_loopback(scenario: str, duration: float, bag: Path) -> None:
    """The baseline: the same run with every node on this host's loopback (no link)."""
    argv = [str(REPO / '.venv' / 'bin' / 'haptic-topology'), 'run', scenario, '--duration',
            f'{duration:g}', '--no-plot', '--out', str(bag)]
    print(f'$ {" ".join(argv)}', flush=True)
    done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f'{scenario} loopback failed ({done.returncode}):\n'
                           f'{done.stdout[-2000:]}\n{done.stderr[-2000:]}')


def run_one(scenario: str, delay: float, duration: float, profile: str, bag: Path,
            prefix: str, loss: float = DEFAULT_LOSS) -> None:
    env = dict(os.environ, OUT=str(bag), HT_PREFIX=prefix, HT_LOSS=f'{loss:g}')
    command = 'run-device' if profile == 'device' else 'run'
    shown = f'HT_LOSS={loss:g}'
    if command == 'run':
        env['HT_DDS_PROFILE'] = profile
        shown += f' HT_DDS_PROFILE={profile}'
    argv = ['bash', str(SCRIPT), command, scenario, f'{delay:g}', '--duration',
            f'{duration:g}', '--no-plot']
    print(f'$ OUT={bag} {shown} {" ".join(argv[1:])}', flush=True)
    done = subprocess.run(argv, env=env, cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f'{scenario} {delay} ms failed ({done.returncode}):\n'
                           f'{done.stdout[-2000:]}\n{done.stderr[-2000:]}')


def offline(scenario: str, duration: float) -> Any:
    from haptic_topology.sim.lockstep import simulate
    from haptic_topology.sim.scenario import load_scenario

    return simulate(replace(load_scenario(scenario), duration=duration))


def path_deviation(live: Any, sim: Any) -> dict[str, float]:
    """Max / RMS distance (m) between the live and the offline device positions at the same
    time since engagement (offline interpolated; live rows past its end left out)."""
    n = 2 if live.task_dim == 3 else 3
    ok = np.isfinite(live.t) & (live.t <= sim.t[-1])
    t = live.t[ok]
    ref = np.stack([np.interp(t, sim.t, sim.columns['device_pose'][:, i]) for i in range(n)],
                   axis=1)
    d = np.linalg.norm(live.columns['device_pose'][ok, :n] - ref, axis=1)
    d = d[np.isfinite(d)]
    return {'max': float(d.max()), 'rms': float(math.sqrt(float(np.mean(d * d))))}


def resync_figures(bag: Path) -> dict[str, Any]:
    """Model age at each update's arrival, the longest gap between updates (ms) and the
    controller's last diagnostics values, from the bag."""
    from haptic_topology.bag.reader import decoder, iter_messages, open_bag

    b = open_bag(bag)
    decode = decoder(bag=b)
    state_time: dict[int, int] = {}
    updates: list[tuple[int, int]] = []
    ctl: dict[str, str] = {}
    drv: dict[str, str] = {}
    for m in iter_messages(b):
        if m.topic.endswith(vocab.TOPIC_STATE):
            state_time.setdefault(int(decode(m).seq), m.log_time)
        elif m.topic.endswith(vocab.TOPIC_LMI):
            updates.append((m.log_time, int(decode(m).hand_input_seq)))
        elif m.topic == vocab.TOPIC_DIAGNOSTICS:
            for st in decode(m).status:
                if st.name == CONTROLLER_STATUS:
                    ctl = {kv.key: kv.value for kv in st.values}
                elif st.name == DRIVER_STATUS:
                    drv = {kv.key: kv.value for kv in st.values}
    # The first update that consumed input s (the VE's keep-alive updates repeat it).
    first_of: dict[int, int] = {}
    for t, s in updates:
        first_of.setdefault(s, t)
    ages = np.array([(t - state_time[s]) * 1e-6 for s, t in first_of.items()
                     if s in state_time])
    first = min(state_time.values()) if state_time else 0
    arrivals = np.array([t for t, s in updates if t >= first], dtype=float) * 1e-6
    gaps = np.diff(arrivals) if arrivals.size > 1 else np.zeros(1)
    return {
        'model_age_p50_ms': float(np.percentile(ages, 50)) if ages.size else None,
        'model_age_p99_ms': float(np.percentile(ages, 99)) if ages.size else None,
        'update_gap_max_ms': float(gaps.max()),
        'updates': int(arrivals.size),
        **{k: ctl.get(k) for k in ('degradations', 'resyncs_held', 'resync_jumps_held',
                                   'dt_capped')},
        **{f'driver_{k}': drv.get(k) for k in ('device_faults', 'fault_cycles',
                                               'watchdog_trips', 'watchdog_cycles')},
    }


def analyse(bag: Path, sim: Any) -> dict[str, Any]:
    from haptic_topology.sim.trace_io import read_trace

    summary = json.loads((bag / 'summary.json').read_text(encoding='utf-8'))
    link_file = bag / 'link.json'
    link: dict[str, Any] = (json.loads(link_file.read_text(encoding='utf-8'))
                            if link_file.is_file() else {'stage': 'loopback'})
    live = read_trace(bag / 'trace.parquet')
    row: dict[str, Any] = {k: summary.get(k) for k in (
        'final_distance_m', 'max_distance_m', 'rms_distance_m', 'workspace_limit_time_s',
        'device_answered_fraction', 'device_period_p99_ms', 'max_consecutive_missed',
        've_update_rate_hz', 'samples')}
    ref = sim.summary()
    row.update({f'offline_{k}': ref[k] for k in ('final_distance_m', 'max_distance_m',
                                                 'rms_distance_m')})
    dev = path_deviation(live, sim)
    row['path_vs_offline_max_m'] = dev['max']
    row['path_vs_offline_rms_m'] = dev['rms']
    row.update(resync_figures(bag))
    row['link_stage'] = link.get('stage')
    total = link.get('total')
    if total:
        row['link'] = {k: total[k] for k in ('received', 'forwarded', 'dropped', 'overtaken',
                                             'send_errors')}
        row['link']['achieved_delay_ms'] = total['achieved_delay_ms']
        row['link']['drawn_delay_ms'] = total['drawn_delay_ms']
        # a_to_b: from the near side (commands, with run-device), b_to_a: to it (states)
        row['link']['dropped_per_direction'] = {
            d: v.get('dropped') for d, v in (link.get('directions') or {}).items()}
    status = live.columns['status'].astype(int)
    row['fault_states'] = int(np.count_nonzero(status & 8))
    row['watchdog_states'] = int(np.count_nonzero(status & 4))
    server_file = bag / 'device_server.json'
    if server_file.is_file():
        srv = json.loads(server_file.read_text(encoding='utf-8'))
        row['server'] = {k: srv.get(k) for k in (
            'cycles', 'missed_deadlines', 'commands', 'applied_cycles', 'lost', 'late',
            'duplicate', 'too_old', 'malformed', 'command_timeouts', 'timeout_cycles',
            'states_sent')}
        cpu_file = bag / 'device_server_cpu.json'
        if cpu_file.is_file():
            cpu = json.loads(cpu_file.read_text(encoding='utf-8'))
            row['server']['cpu'] = cpu['cpu_s'] / cpu['wall_s'] if cpu.get('wall_s') else None
    return row


def _mm(v: float | None) -> str:
    return '-' if v is None else f'{v * 1e3:.3f}'


def _f(v: Any, fmt: str) -> str:
    return '-' if v is None else format(float(v), fmt)


def table(rows: list[dict[str, Any]]) -> str:
    head = ('| DDS profile | scenario | delay [ms] | drift final / max / RMS [mm] | offline final '
            '/ max / RMS [mm] | path vs offline max / RMS [mm] | model age at update p50 / '
            'p99 [ms] | longest update gap [ms] | degradations | answered [%] | period p99 '
            '[ms] | link: forwarded / dropped, delay p50 / p99 [ms] |')
    out = [head, '|' + '---|' * head.count(' | ') + '---|']
    for r in rows:
        link = r.get('link') or {}
        ach = link.get('achieved_delay_ms') or {}
        link_txt = (f'{link.get("forwarded")} / {link.get("dropped")}, '
                    f'{_f(ach.get("p50"), ".2f")} / {_f(ach.get("p99"), ".2f")}'
                    if link else r.get('link_stage') or '-')
        delay = 'none' if r['delay_ms'] is None else f'{r["delay_ms"]:g}'
        if r['delay_ms'] is not None and r.get('loss', DEFAULT_LOSS) != DEFAULT_LOSS:
            delay += f' (loss {r["loss"] * 100:g} %)'
        out.append(
            f'| {r["profile"]} | {r["scenario"]} | {delay} | '
            f'{_mm(r["final_distance_m"])} / {_mm(r["max_distance_m"])} / '
            f'{_mm(r["rms_distance_m"])} | {_mm(r["offline_final_distance_m"])} / '
            f'{_mm(r["offline_max_distance_m"])} / {_mm(r["offline_rms_distance_m"])} | '
            f'{_mm(r["path_vs_offline_max_m"])} / {_mm(r["path_vs_offline_rms_m"])} | '
            f'{_f(r["model_age_p50_ms"], ".1f")} / {_f(r["model_age_p99_ms"], ".1f")} | '
            f'{r["update_gap_max_ms"]:.0f} | {r.get("degradations") or "-"} | '
            f'{_f(r["device_answered_fraction"] * 100 if r["device_answered_fraction"] is not None else None, ".1f")} | '  # noqa: E501
            f'{_f(r["device_period_p99_ms"], ".2f")} | {link_txt} |')
    return '\n'.join(out)


def device_table(rows: list[dict[str, Any]]) -> str:
    """The device side (``--remote-device``): drift, loop figures, FAULT / WATCHDOG states,
    the driver's fault onsets / cycles, the server's command timeouts (cycles at zero), lost /
    late commands, missed deadlines and CPU, frames dropped by the link (commands / states)."""
    head = ('| device | scenario | link | drift final / max / RMS [mm] | path vs offline max / '
            'RMS [mm] | answered [%] | period p99 [ms] | FAULT / WATCHDOG states | driver fault'
            ' onsets / cycles | server timeouts (cycles at 0) | commands lost / late | server '
            'missed deadlines / cycles, CPU | link dropped commands / states |')
    out = [head, '|' + '---|' * head.count(' | ') + '---|']
    for r in rows:
        srv = r.get('server') or {}
        link = r.get('link') or {}
        per = link.get('dropped_per_direction') or {}
        if r['profile'] in DEVICE_PROFILES:
            device = 'device-server'
        else:
            device = 'sim_maglev' if r['profile'] == 'loopback' else f'sim_maglev ({r["profile"]})'
        where = ('loopback' if r['delay_ms'] is None else
                 f'{r["delay_ms"]:g} ms +-20 %, {r.get("loss", DEFAULT_LOSS) * 100:g} % loss')
        cpu = srv.get('cpu')
        out.append(
            f'| {device} | {r["scenario"]} | {where} | '
            f'{_mm(r["final_distance_m"])} / {_mm(r["max_distance_m"])} / '
            f'{_mm(r["rms_distance_m"])} | '
            f'{_mm(r["path_vs_offline_max_m"])} / {_mm(r["path_vs_offline_rms_m"])} | '
            f'{_f(r["device_answered_fraction"] * 100 if r["device_answered_fraction"] is not None else None, ".1f")} | '  # noqa: E501
            f'{_f(r["device_period_p99_ms"], ".2f")} | '
            f'{r.get("fault_states", "-")} / {r.get("watchdog_states", "-")} | '
            f'{r.get("driver_device_faults") or "-"} / {r.get("driver_fault_cycles") or "-"} | '
            + (f'{srv.get("command_timeouts")} ({srv.get("timeout_cycles")}) | '
               f'{srv.get("lost")} / {srv.get("late")} | '
               f'{srv.get("missed_deadlines")} / {srv.get("cycles")}, '
               f'{_f(cpu, ".2f")} | ' if srv else '- | - | - | ')
            + (f'{per.get("a_to_b")} / {per.get("b_to_a")} |' if per else '- |'))
    return '\n'.join(out)


def plot(rows: list[dict[str, Any]], path: Path,
         repeats: list[dict[str, Any]] | None = None) -> None:
    """Drift (final/max/RMS) against delay per scenario, and the model age at re-sync;
    ``repeats``: rows of repeated runs, drawn as open markers."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    scenarios = list(dict.fromkeys(r['scenario'] for r in rows))
    profiles = list(dict.fromkeys(r['profile'] for r in rows))
    fig, axes = plt.subplots(1, len(scenarios) + 1, figsize=(5.2 * (len(scenarios) + 1), 4.2),
                             squeeze=False)
    styles = {'two_hosts': '-', 'default': '--'}
    colors = {'final_distance_m': 'C0', 'max_distance_m': 'C3', 'rms_distance_m': 'C2'}
    for ax, sc in zip(axes[0], scenarios, strict=False):
        for prof in profiles:
            rs = sorted((r for r in rows if r['scenario'] == sc and r['profile'] == prof),
                        key=lambda r: r['delay_ms'] if r['delay_ms'] is not None else -1)
            if not rs:
                continue
            if rs[0]['delay_ms'] is None:       # the loopback baseline: no link
                for key, c in colors.items():
                    ax.axhline(rs[0][key] * 1e3, color=c, lw=0.8, ls='-.')
                continue
            d = [r['delay_ms'] for r in rs]
            for key, c in colors.items():
                ax.plot(d, [r[key] * 1e3 for r in rs], styles.get(prof, ':'), color=c,
                        marker='o', label=f'{key.split("_")[0]} ({prof})')
        for r in repeats or ():
            if r['scenario'] == sc and r['delay_ms'] is not None:
                for key, c in colors.items():
                    ax.plot([r['delay_ms']], [r[key] * 1e3], 'o', mfc='none', color=c)
        rs = [r for r in rows if r['scenario'] == sc]
        for key, c in colors.items():
            ax.axhline(rs[0][f'offline_{key}'] * 1e3, color=c, lw=0.8, ls=':')
        ax.set_title(f'{sc}: drift vs one-way delay')
        ax.set_xlabel('one-way delay [ms] (+-20 % jitter, 1 % loss)')
        ax.set_ylabel('device - VT hand [mm]')
        ax.set_yscale('log')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(fontsize=7)
    ax = axes[0][-1]
    for i, sc in enumerate(scenarios):
        for prof in profiles:
            rs = sorted((r for r in rows if r['scenario'] == sc and r['profile'] == prof
                         and r['model_age_p50_ms'] is not None
                         and r['delay_ms'] is not None), key=lambda r: r['delay_ms'])
            if not rs:
                continue
            d = [r['delay_ms'] for r in rs]
            ax.plot(d, [r['model_age_p50_ms'] for r in rs], styles.get(prof, ':'),
                    color=f'C{i}', marker='o', label=f'{sc} p50 ({prof})')
            ax.plot(d, [r['model_age_p99_ms'] for r in rs], styles.get(prof, ':'),
                    color=f'C{i}', marker='^', alpha=0.6, label=f'{sc} p99 ({prof})')
    ax.set_title('model age when an LMI update arrives\n(inputs the LMI replays, ms)')
    ax.set_xlabel('one-way delay [ms]')
    ax.set_ylabel('ms')
    ax.set_yscale('log')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=7)
    fig.suptitle('solid: config/fastdds_two_hosts.xml, dashed: Fast DDS defaults; dotted: '
                 'offline simulate; dash-dot: loopback (no link); open markers: repeated runs',
                 fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--scenarios', nargs='+', default=['fig8', 'circle'])
    p.add_argument('--delays', nargs='+', type=float,
                   help='one-way delays, ms (default 0 5 20 50; --remote-device: 1)')
    p.add_argument('--losses', nargs='+', type=float,
                   help='frame loss probabilities of the link (default 0.01; --remote-device: '
                   '0 0.01)')
    p.add_argument('--remote-device', action='store_true',
                   help='the device server behind the link instead of the VE (module doc)')
    p.add_argument('--circle-duration', type=float, default=10.0,
                   help='s (fig8 and others: the scenario duration)')
    p.add_argument('--profiles', nargs='+',
                   choices=('loopback', 'two_hosts', 'default', *DEVICE_PROFILES),
                   help='default loopback two_hosts; --remote-device: loopback device_loopback '
                   'device')
    p.add_argument('--out', type=Path,
                   help='default bags/two_hosts; --remote-device: bags/two_hosts_device')
    p.add_argument('--plot', type=Path, help='default docs/img/two_hosts_delay.png; '
                   '--remote-device: none')
    p.add_argument('--reuse', action='store_true', help='analyse existing bags, run nothing')
    p.add_argument('--repeats', nargs='*', type=Path, default=[], metavar='RESULTS_JSON',
                   help='results.json of repeated runs, drawn as open markers in the plot')
    args = p.parse_args(argv)
    remote = args.remote_device
    if args.delays is None:
        args.delays = [1.0] if remote else [0.0, 5.0, 20.0, 50.0]
    if args.losses is None:
        args.losses = [0.0, DEFAULT_LOSS] if remote else [DEFAULT_LOSS]
    if args.profiles is None:
        args.profiles = (['loopback', *DEVICE_PROFILES] if remote
                         else ['loopback', 'two_hosts'])
    if args.out is None:
        args.out = REPO / 'bags' / ('two_hosts_device' if remote else 'two_hosts')
    if args.plot is None and not remote:
        args.plot = REPO / 'docs' / 'img' / 'two_hosts_delay.png'
    if not args.reuse and os.geteuid() != 0:
        print('two_hosts_delay: skipped: needs root (network namespaces); run it with sudo')
        return 0
    from haptic_topology.sim.scenario import load_scenario

    args.out.mkdir(parents=True, exist_ok=True)
    prefix = f'htb{os.getpid() % 10000}_'
    rows = []
    sims: dict[str, Any] = {}
    for profile in args.profiles:
        for sc in args.scenarios:
            duration = args.circle_duration if sc == 'circle' else load_scenario(sc).duration
            if sc not in sims:
                sims[sc] = offline(sc, duration)
            cells: list[tuple[float | None, float]] = (
                [(None, 0.0)] if profile in ('loopback', 'device_loopback')
                else [(d, loss) for d in args.delays for loss in args.losses])
            for delay, loss in cells:
                bag = args.out / bag_name(profile, sc, delay, loss)
                if not args.reuse:
                    if bag.exists():
                        raise SystemExit(f'{bag} exists (remove it, or --reuse)')
                    if profile == 'loopback':
                        run_loopback(sc, duration, bag)
                    elif profile == 'device_loopback':
                        run_device_loopback(sc, duration, bag)
                    else:
                        assert delay is not None
                        run_one(sc, delay, duration, profile, bag, prefix, loss)
                if not (bag / 'summary.json').is_file():
                    print(f'{bag}: no summary.json, left out', file=sys.stderr)
                    continue
                row = {'profile': profile, 'scenario': sc, 'delay_ms': delay,
                       'loss': None if delay is None else loss,
                       'duration_s': duration, 'bag': str(bag), **analyse(bag, sims[sc])}
                rows.append(row)
                print(table([row]).splitlines()[-1], flush=True)
    (args.out / 'results.json').write_text(json.dumps(rows, indent=1) + '\n', encoding='utf-8')
    print()
    print(table(rows))
    if any(r['profile'] in DEVICE_PROFILES for r in rows):
        print()
        print(device_table(rows))
    if rows and args.plot is not None and str(args.plot):
        repeats = [r for f in args.repeats
                   for r in json.loads(f.read_text(encoding='utf-8'))]
        plot(rows, args.plot, repeats)
        print(f'\nplot: {args.plot}')
    print(f'results: {args.out / "results.json"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
