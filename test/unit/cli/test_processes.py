"""haptic_topology.processes: children, command lines and the resident-set sampler that
``run`` reports as ``rss_mb_<process>`` and ``rss_growth_kb_s_<process>``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import pytest

from haptic_topology.processes import (
    RSS_SETTLE,
    STACKS_SIGNAL,
    RssSampler,
    RunUsage,
    children,
    cmdline,
    rss_bytes,
    stacks_on_signal,
)


def test_children_and_cmdline_of_a_child() -> None:
    code = 'import time; print("up", flush=True); time.sleep(30)'
    p = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout is not None
        assert p.stdout.readline().strip() == 'up'      # it runs its own program by now
        assert p.pid in children(os.getpid())
        assert cmdline(p.pid) == [sys.executable, '-c', code]
        assert rss_bytes(p.pid) is not None and rss_bytes(p.pid) > 0
    finally:
        p.kill()
        p.wait()
    assert p.pid not in children(os.getpid())
    assert cmdline(p.pid) == []
    assert rss_bytes(p.pid) is None


def _add(s: RssSampler, name: str, pts: list[tuple[float, int]]) -> None:
    for t, r in pts:
        s.add(name, t, r)


def test_growth_is_the_slope_after_the_settling_time() -> None:
    s = RssSampler(lambda: {})
    # 10 kB/s before RSS_SETTLE (left out), then 2.5 kB/s; one process with too few samples
    t_end = RSS_SETTLE + 100.0
    pts = [(float(t), 10_000 * t if t < RSS_SETTLE else 10_000 * RSS_SETTLE
            + 2_500 * (t - RSS_SETTLE)) for t in range(0, int(t_end) + 1)]
    _add(s, 'a', [(t, int(r)) for t, r in pts])
    _add(s, 'b', [(0.0, 1 << 20), (1.0, 1 << 20)])
    g = s.growth()
    assert g['a']['growth_kb_s'] == pytest.approx(2.5, abs=1e-9)
    assert g['a']['from_s'] == RSS_SETTLE
    assert g['a']['rss_mb'] == round(pts[-1][1] / 2 ** 20, 2)
    assert 'growth_kb_s' not in g['b'] and g['b']['rss_mb'] == 1.0
    # first and largest sample (a bump in the middle is the peak)
    _add(s, 'c', [(0.0, 3 << 20), (1.0, 5 << 20), (2.0, 4 << 20)])
    assert (s.growth()['c']['start_mb'], s.growth()['c']['peak_mb']) == (3.0, 5.0)


def test_a_short_run_is_fitted_over_its_second_half() -> None:
    s = RssSampler(lambda: {})
    _add(s, 'a', [(float(t), 1000 * t * t) for t in range(21)])
    g = s.growth()['a']
    assert g['from_s'] == 10.0
    # d(t^2)/dt over t in [10, 20] by least squares: 2 * 15 = 30 (1000 bytes/s units)
    assert g['growth_kb_s'] == pytest.approx(30.0, abs=1e-9)


def test_the_sampler_samples_a_live_process() -> None:
    s = RssSampler(lambda: {'me': os.getpid(), 'gone': 2 ** 22 + 1}, period=0.01)
    s.start()
    try:
        while 'me' not in s.tracks or len(s.tracks['me'].early) < 3:
            s.sample()
    finally:
        s.stop()
    assert 'gone' not in s.tracks
    assert all(r > 0 for _, r in s.tracks['me'].early)


def test_run_usage_finds_the_child_and_leaves_its_start_up_out() -> None:
    """A parent whose child burns CPU before and after start(): the child is found by its
    module, its CPU before start() is left out, and it is counted once reaped."""
    burn = ('import sys, time\n'
            'def spin(s):\n'
            '    t = time.process_time()\n'
            '    while time.process_time() - t < s:\n'
            '        pass\n'
            'spin(0.4); sys.stdout.write("up\\n"); sys.stdout.flush(); sys.stdin.readline()\n'
            'spin(0.3)\n')
    parent_code = ('import subprocess, sys\n'
                   f'p = subprocess.Popen([sys.executable, "-c", {burn!r}, "burner_marker"],\n'
                   '                     stdin=subprocess.PIPE, stdout=subprocess.PIPE)\n'
                   'p.stdout.readline(); print("ready", flush=True)\n'
                   'sys.stdin.readline(); p.stdin.write(b"go\\n"); p.stdin.flush(); p.wait()\n'
                   'print("done", flush=True); sys.stdin.readline()\n')
    parent = subprocess.Popen([sys.executable, '-c', parent_code], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None and parent.stdin is not None
        assert parent.stdout.readline().strip() == 'ready'
        usage = RunUsage({'parent': parent.pid}, parent.pid, 'burner_marker', 'burner')
        assert usage.child() is not None
        usage.start()
        parent.stdin.write('\n')
        parent.stdin.flush()
        assert parent.stdout.readline().strip() == 'done'
        usage.stop()
        assert usage.child() is None
        cpu = usage.cpu(1.0)
        # 0.3 s after start(), not the 0.7 s of its whole life (clock ticks: 10 ms)
        assert 0.25 <= cpu['burner'] <= 0.45, cpu
        assert 'parent' in cpu
    finally:
        parent.kill()
        parent.wait()


def test_the_series_keeps_a_sample_every_step() -> None:
    s = RssSampler(lambda: {})
    _add(s, 'a', [(0.5 * k, (1 << 20) * (1 + k)) for k in range(61)])     # 30 s
    series = s.growth()['a']['series']
    assert [t for t, _ in series] == [0.0, 10.0, 20.0, 30.0]
    assert series[1][1] == 21.0      # MiB at 10 s


def test_an_hours_samples_take_no_more_memory_than_ten_minutes() -> None:
    """``run`` samples every process every second for as long as it runs: what it keeps
    must not grow with the run (it grew 3.1 kB/s over an hour's soak), while the fit still
    equals the least squares over every sample after the settling time."""
    def kept(seconds: int) -> tuple[int, float]:
        s = RssSampler(lambda: {})
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        for k in range(seconds):
            for name in ('recorder', 've_sim', 'device_driver', 'loop_process', 'run'):
                s.add(name, float(k), 300_000_000 + 1234 * k + (k * 7919) % 5000)
        used = tracemalloc.get_traced_memory()[0] - before
        tracemalloc.stop()
        return used, s.growth()['run']['growth_kb_s']
    used_10min, _ = kept(600)
    used_hour, slope = kept(3600)
    # the only part that grows: one series point per 10 s (5 processes x 300 points)
    assert used_hour - used_10min < 5 * 300 * 200, (used_10min, used_hour)
    ts = [float(k) for k in range(int(RSS_SETTLE), 3600)]
    rs = [300_000_000 + 1234 * k + (k * 7919) % 5000 for k in range(int(RSS_SETTLE), 3600)]
    tm, rm = sum(ts) / len(ts), sum(rs) / len(rs)
    expect = (sum((t - tm) * (r - rm) for t, r in zip(ts, rs, strict=True))
              / sum((t - tm) ** 2 for t in ts))
    assert slope == round(expect / 1000.0, 3)


def test_run_starts_a_node_in_its_session_and_a_process_group_of_its_own(
        tmp_path: Path) -> None:
    """One session for the graph (the kernel's autogroup then weighs the loop against the
    nodes' threads, not against whole sessions); a process group per node, so the
    terminal's Ctrl-C reaches only ``run``, which stops the nodes in order."""
    from haptic_topology.bringup.run import _start, stop

    node = _start('sleeper', [sys.executable, '-c', 'import time; time.sleep(30)'], tmp_path)
    try:
        assert os.getsid(node.popen.pid) == os.getsid(0)
        assert os.getpgid(node.popen.pid) == node.popen.pid != os.getpgid(0)
    finally:
        stop([node], timeout=5.0)
    assert node.popen.poll() is not None



def _stacks_after_sigusr1(argv: list[str], ready: str, err: Path,
                          expect: tuple[str, ...]) -> str:
    """Start ``argv`` (stderr to ``err``), wait for a stdout line starting with ``ready``,
    send SIGUSR1 and wait until its stderr holds every string of ``expect`` (60 s at most:
    no timing is asserted); the process must still run then. Returns its stderr."""
    with err.open('wb') as out:
        p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=out, text=True)
    try:
        assert p.stdout is not None
        line = p.stdout.readline()
        assert line.startswith(ready), line + err.read_text()
        p.send_signal(signal.SIGUSR1)
        deadline = time.monotonic() + 60.0
        while (not all(e in err.read_text() for e in expect)
               and time.monotonic() < deadline):
            time.sleep(0.05)
        assert p.poll() is None, err.read_text()    # it goes on
    finally:
        p.kill()
        p.wait()
    return err.read_text()


def test_sigusr1_writes_every_threads_stack_and_the_process_goes_on(tmp_path: Path) -> None:
    code = ('import threading, time\n'
            'from haptic_topology.processes import stacks_on_signal\n'
            'stacks_on_signal()\n'
            'def worker():\n'
            '    time.sleep(600)\n'
            'def main():\n'
            '    threading.Thread(target=worker, daemon=True).start()\n'
            '    print("up", flush=True)\n'
            '    time.sleep(600)\n'
            'main()\n')
    expect = ('Thread 0x', 'in worker', 'in main')
    text = _stacks_after_sigusr1([sys.executable, '-c', code], 'up', tmp_path / 'err', expect)
    assert all(e in text for e in expect), text


def test_the_command_line_writes_its_stacks_on_sigusr1(tmp_path: Path) -> None:
    # A command that runs until stopped: the device server.
    argv = [sys.executable, '-m', 'haptic_topology.cli', 'device-server', '--scenario',
            'circle', '--host', '127.0.0.1', '--port', '0']
    expect = ('Current thread 0x', 'haptic_topology/cli.py')
    text = _stacks_after_sigusr1(argv, 'device-server: serving', tmp_path / 'err', expect)
    assert all(e in text for e in expect), text


def test_without_a_stderr_file_no_handler_is_registered(monkeypatch: pytest.MonkeyPatch) -> None:
    # A caller that captured stderr (pytest, an IDE): the command still runs.
    import faulthandler
    import io

    faulthandler.unregister(STACKS_SIGNAL)      # whatever this process registered before
    monkeypatch.setattr(sys, 'stderr', io.StringIO())
    assert stacks_on_signal() is False
    assert faulthandler.unregister(STACKS_SIGNAL) is False      # nothing was registered
