"""Child processes and their CPU time, from ``/proc`` and signals (no ROS): what the bringup,
the benchmarks and the tests share."""

from __future__ import annotations

import faulthandler
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: The signal on which a process of this package writes every thread's Python stack to its
#: stderr (a node's: its log) and goes on: ``kill -USR1 PID`` shows where a run hangs.
STACKS_SIGNAL = signal.SIGUSR1


def stacks_on_signal() -> bool:
    """Have :data:`STACKS_SIGNAL` write every thread's Python stack to stderr
    (:func:`faulthandler.register`: written from the signal handler, no GIL needed, so a
    thread stuck holding it shows too). Returns False, registering nothing, when stderr is
    no file (a caller that captures it, as pytest does): there is nowhere to write to."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):   # io.UnsupportedOperation among them
        return False
    faulthandler.register(STACKS_SIGNAL, file=fd, all_threads=True)
    return True


def stat_fields(path: str) -> list[str] | None:
    """The fields of a ``/proc/<pid>[/task/<tid>]/stat`` file after the command name (the
    state first, as ``proc(5)`` numbers them from 3); None once it is gone. One ``read``
    (:mod:`haptic_topology.bringup.partition` reads every process's twice a second)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        return os.read(fd, 4096).decode('ascii', 'replace').rsplit(')', 1)[1].split()
    except (OSError, IndexError):
        return None
    finally:
        os.close(fd)


def thread_ids(pid: int) -> list[int]:
    """The ids of process ``pid``'s threads (empty once it is gone)."""
    try:
        return [int(t) for t in os.listdir(f'/proc/{pid}/task')]
    except OSError:
        return []


def running(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie waiting to be reaped does not)."""
    fields = stat_fields(f'/proc/{pid}/stat')
    return fields is not None and fields[0] != 'Z'


def cpu_seconds(pid: int, tid: int | None = None) -> float | None:
    """User + system CPU time (s) of process ``pid`` (all its threads), or of its thread
    ``tid``, from ``/proc``; None once it is gone."""
    fields = stat_fields(f'/proc/{pid}/stat' if tid is None else f'/proc/{pid}/task/{tid}/stat')
    if fields is None:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def reaped_children_cpu_seconds(pid: int) -> float | None:
    """User + system CPU time (s) of the children of ``pid`` that have ended and that it has
    waited for (e.g. ``device_driver``'s loop process after a run), from ``/proc``; None once
    ``pid`` is gone."""
    fields = stat_fields(f'/proc/{pid}/stat')
    if fields is None:
        return None
    return (int(fields[13]) + int(fields[14])) / os.sysconf('SC_CLK_TCK')


def children(pid: int) -> list[int]:
    """The running children of process ``pid`` (of any of its threads), from ``/proc``;
    empty once it is gone."""
    out: list[int] = []
    for tid in thread_ids(pid):
        try:
            out += [int(c) for c in Path(f'/proc/{pid}/task/{tid}/children').read_text().split()]
        except OSError:
            continue
    return out


def cmdline(pid: int) -> list[str]:
    """The command line of process ``pid`` (empty once it is gone)."""
    try:
        raw = Path(f'/proc/{pid}/cmdline').read_bytes()
    except OSError:
        return []
    return [a.decode(errors='replace') for a in raw.split(b'\0') if a]


def rss_bytes(pid: int) -> int | None:
    """Resident set size (bytes) of process ``pid`` (``/proc/<pid>/statm``); None once it is
    gone."""
    try:
        resident = int(Path(f'/proc/{pid}/statm').read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    return resident * os.sysconf('SC_PAGE_SIZE')


#: Seconds from the start of a run after which :meth:`RssSampler.growth` fits the resident
#: set (start-up allocations, caches filling), or half the run when it is shorter.
RSS_SETTLE = 60.0


class Periodic:
    """Calls :meth:`sample` at once and then every ``period`` s in a daemon thread of its own
    (named ``name``), from :meth:`start` to :meth:`stop`; ``_t0`` is when it started
    (monotonic s). :meth:`begin` runs first in that thread."""

    name = 'periodic'

    def __init__(self, period: float) -> None:
        self.period = period
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()

    def start(self) -> None:
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._body, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def begin(self) -> None:
        """The thread's set-up (nothing here)."""

    def sample(self) -> None:
        raise NotImplementedError

    def _body(self) -> None:
        self.begin()
        self.sample()
        while not self._stop.wait(self.period):
            self.sample()


class RssTrack:
    """The resident-set samples of one process in bounded memory (a run may last hours).

    Keeps the first, last and largest sample, one ``[s, MiB]`` point per ``series_step`` s,
    every sample of the first ``2 * RSS_SETTLE`` s (the fit of a run shorter than that is over
    its second half) and, from ``RSS_SETTLE`` s on, the running means and co-moments of time
    and resident set (Welford's update) that the least-squares slope needs."""

    __slots__ = ('first', 'last', 'peak', 'series', 'series_step', 'early', 'n', 't_mean',
                 'r_mean', 'c_tr', 'm_tt')

    def __init__(self, series_step: float = 10.0) -> None:
        self.series_step = series_step
        self.first: tuple[float, int] | None = None
        self.last: tuple[float, int] = (0.0, 0)
        self.peak = 0
        self.series: list[list[float]] = []
        self.early: list[tuple[float, int]] = []
        self.n, self.t_mean, self.r_mean, self.c_tr, self.m_tt = 0, 0.0, 0.0, 0.0, 0.0

    def add(self, t: float, rss: int) -> None:
        """One sample: ``t`` s from the start, ``rss`` bytes (``t`` not decreasing)."""
        if self.first is None:
            self.first = (t, rss)
        self.last = (t, rss)
        self.peak = max(self.peak, rss)
        if not self.series or t - self.series[-1][0] >= self.series_step:
            self.series.append([round(t, 1), round(rss / 2 ** 20, 3)])
        if t < 2.0 * RSS_SETTLE:
            self.early.append((t, rss))
        if t >= RSS_SETTLE:
            self.n += 1
            dt = t - self.t_mean
            self.t_mean += dt / self.n
            self.r_mean += (rss - self.r_mean) / self.n
            self.c_tr += dt * (rss - self.r_mean)
            self.m_tt += dt * (t - self.t_mean)

    def slope(self, since: float) -> float | None:
        """The least-squares slope (bytes/s) of the samples from ``since`` s on (``since`` is
        ``RSS_SETTLE`` or, for a run shorter than ``2 * RSS_SETTLE``, half of it); None with
        fewer than 3 samples or no spread in time."""
        if since >= RSS_SETTLE:
            n, c_tr, m_tt = self.n, self.c_tr, self.m_tt
        else:
            fit = [(t, r) for t, r in self.early if t >= since]
            n = len(fit)
            tm = sum(t for t, _ in fit) / n if n else 0.0
            rm = sum(r for _, r in fit) / n if n else 0.0
            c_tr = sum((t - tm) * (r - rm) for t, r in fit)
            m_tt = sum((t - tm) ** 2 for t, _ in fit)
        if n < 3 or m_tt <= 0.0:
            return None
        return c_tr / m_tt


class RssSampler(Periodic):
    """Samples the resident set of named processes every ``period`` s in a thread of its own
    (``pids()`` returns ``{name: pid}`` at each sample: a process may come and go), in
    memory that does not grow with the run (:class:`RssTrack`).

    :meth:`growth` is the least-squares slope of each process's resident set (bytes/s) over
    its samples after :data:`RSS_SETTLE` s (or after half the run)."""

    name = 'rss_sampler'

    def __init__(self, pids: Callable[[], dict[str, int]], period: float = 1.0,
                 series_step: float = 10.0) -> None:
        super().__init__(period)
        self._pids = pids
        self.series_step = series_step
        self.tracks: dict[str, RssTrack] = {}

    def add(self, name: str, t: float, rss: int) -> None:
        """Record one sample of process ``name``: ``t`` s from the start, ``rss`` bytes."""
        track = self.tracks.get(name)
        if track is None:
            track = self.tracks[name] = RssTrack(self.series_step)
        track.add(t, rss)

    def sample(self) -> None:
        """Take one sample of every process now."""
        t = time.monotonic() - self._t0
        for name, pid in self._pids().items():
            rss = rss_bytes(pid)
            if rss is not None:
                self.add(name, t, rss)

    def growth(self) -> dict[str, dict[str, Any]]:
        """Per process: ``rss_mb`` (the last sample, MiB), ``start_mb`` and ``peak_mb`` (the
        first and the largest sample, MiB), ``growth_kb_s`` (kB/s, 1 kB = 1000 bytes),
        ``from_s`` (the fit's first second) and ``series`` (``[s, MiB]`` pairs at least
        ``series_step`` s apart); a process with fewer than 3 samples in the fit's window has
        no ``growth_kb_s``."""
        out: dict[str, dict[str, Any]] = {}
        for name, tr in self.tracks.items():
            assert tr.first is not None
            since = min(RSS_SETTLE, 0.5 * tr.last[0])
            entry: dict[str, Any] = {'rss_mb': round(tr.last[1] / 2 ** 20, 2),
                                     'start_mb': round(tr.first[1] / 2 ** 20, 2),
                                     'peak_mb': round(tr.peak / 2 ** 20, 2),
                                     'from_s': round(since, 1), 'series': list(tr.series)}
            slope = tr.slope(since)
            if slope is not None:
                entry['growth_kb_s'] = round(slope / 1000.0, 3)
            out[name] = entry
        return out


def process_times(pid: int) -> dict[str, float] | None:
    """``cpu_s`` (user + system, s) and ``wall_s`` (age, s) of a running process; None once
    it is gone."""
    fields = stat_fields(f'/proc/{pid}/stat')
    try:
        uptime = float(Path('/proc/uptime').read_text().split()[0])
    except OSError:
        return None
    if fields is None:
        return None
    hz = os.sysconf('SC_CLK_TCK')
    return {'cpu_s': (int(fields[11]) + int(fields[12])) / hz,
            'wall_s': uptime - int(fields[19]) / hz}


#: s a stopped process gets after SIGINT before SIGTERM (:func:`terminate`); a node's
#: teardown is bounded below it (the recorder's ``CLOSE_TIMEOUT``)
STOP_TIMEOUT = 5.0
#: s after SIGTERM before SIGKILL (the node processes keep their SIGINT handler through their
#: teardown, so for them only the SIGKILL, ``STOP_TIMEOUT + STOP_ESCALATE`` after the SIGINT,
#: ends it)
STOP_ESCALATE = 2.0


def terminate(popen: subprocess.Popen[Any], timeout: float = STOP_TIMEOUT,
              escalate: float = STOP_ESCALATE) -> int:
    """SIGINT ``popen``, then SIGTERM and SIGKILL if it has not exited after ``timeout`` /
    ``escalate`` seconds; return its exit code."""
    for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, escalate),
                      (signal.SIGKILL, escalate)):
        if popen.poll() is not None:
            break
        popen.send_signal(sig)
        try:
            popen.wait(wait)
        except subprocess.TimeoutExpired:
            continue
    return popen.wait()


class RunUsage:
    """CPU and resident set of a run's processes from :meth:`start` to :meth:`stop`.

    ``pids``: the processes by name; ``parent``: the one whose child runs ``child_module``
    (``python -m``; counted as ``child_name``). The child may end before :meth:`stop` (its
    parent has waited for it: its CPU is read from the parent's reaped children); its CPU
    before :meth:`start` (its start-up) is left out, as the others'."""

    def __init__(self, pids: dict[str, int], parent: int | None = None,
                 child_module: str = '', child_name: str = 'child') -> None:
        self.pids, self.parent = pids, parent
        self.child_module, self.child_name = child_module, child_name
        self._cpu0: dict[str, float | None] = {}
        self._reaped0: float | None = None
        self._t0 = self._t1 = 0.0
        self.rss = RssSampler(self._sampled)

    def child(self) -> int | None:
        """The pid of the parent's running child that runs ``child_module`` (None: none)."""
        for pid in children(self.parent) if self.parent is not None else []:
            if self.child_module in cmdline(pid):
                return pid
        return None

    def _sampled(self) -> dict[str, int]:
        out = {name: pid for name, pid in self.pids.items() if running(pid)}
        child = self.child()
        if child is not None:
            out[self.child_name] = child
        return out

    def start(self) -> None:
        self._t0 = time.monotonic()
        self._cpu0 = {name: cpu_seconds(pid) for name, pid in self.pids.items()}
        if self.parent is not None:
            self._reaped0 = reaped_children_cpu_seconds(self.parent)
            child = self.child()
            if self._reaped0 is not None and child is not None:
                self._reaped0 += cpu_seconds(child) or 0.0
        self.rss.start()

    def stop(self) -> None:
        self._t1 = time.monotonic()
        self.rss.stop()

    def cpu(self, wall: float | None = None) -> dict[str, float]:
        """Fraction of a core per process over ``wall`` s (default: from :meth:`start` to
        :meth:`stop`), read now; the child's once its parent has reaped it."""
        wall = self._t1 - self._t0 if wall is None else wall
        out: dict[str, float] = {}
        if wall <= 0.0:
            return out
        for name, pid in self.pids.items():
            c0, c1 = self._cpu0.get(name), cpu_seconds(pid)
            if c0 is not None and c1 is not None:
                out[name] = round((c1 - c0) / wall, 4)
        reaped = (reaped_children_cpu_seconds(self.parent) if self.parent is not None
                  else None)
        if self._reaped0 is not None and reaped is not None and reaped > self._reaped0:
            out[self.child_name] = round((reaped - self._reaped0) / wall, 4)
        return out

