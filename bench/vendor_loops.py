"""``make bench`` section 9: the vendor backends' loop against ``sim_maglev``'s, on emulators.

``haptic-topology run fig8_point`` in the default hosted layout, ``--loop-duration`` s each,
with ``sim_maglev`` and with each vendor backend whose emulator the setup built, configured
as its documented command runs it (``config/devices/<backend>_emulator.yaml``, the
variable that points the vendor's binding at the emulator):

* ``forcedimension``: forcedimension-core against the libdrd emulator on its own clock
  (``FDSDK=<venv>/fdsdk-emulator``);
* ``openhaptics``: pyOpenHaptics against the libHD emulator, whose 1 kHz scheduler thread
  calls the servo callback in which the loop's cycle runs
  (``HAPTIC_TOPOLOGY_LIBHD=<venv>/lib/haptic_topology/libHD.so``);
* ``haply``: the Inverse Service's WebSocket protocol against its emulator
  (``python -m haptic_topology.remote.haply_emulator``), when the backend is there.

Printed per backend: answered %, longest missed run, period p99, and each as a ratio to
``sim_maglev``'s of the same session (and to the machine's floor, when the caller gives it).
A backend whose emulator is missing is listed as not run; a run that fails is listed with
its last line, and the others still count.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
VENV = Path(sys.prefix)
SCENARIO = 'fig8_point'


def _driver_params(backend: str) -> dict[str, Any]:
    """The device_driver parameters of ``config/devices/<backend>_emulator.yaml`` (for
    ``haply``, whose documented command is ``run fig8_point --backend haply``: the
    backend alone)."""
    path = ROOT / 'config' / 'devices' / f'{backend}_emulator.yaml'
    if not path.is_file():
        return {'backend': backend}
    doc = yaml.safe_load(path.read_text(encoding='utf-8'))
    return dict(doc['device_driver']['ros__parameters'])


@contextmanager
def _nothing() -> Iterator[None]:
    yield


@contextmanager
def _haply_service() -> Iterator[None]:
    """The Inverse Service emulator on its default port while the run lasts."""
    with tempfile.TemporaryDirectory(prefix='bench_haply_') as tmp:
        ready = Path(tmp) / 'ready.json'
        proc = subprocess.Popen([sys.executable, '-m', 'haptic_topology.remote.haply_emulator',
                                 '--ready-file', str(ready)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 60.0
            while not ready.exists():
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError('the Haply service emulator did not start')
                time.sleep(0.05)
            yield
        finally:
            _stop(proc)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def backends() -> list[tuple[str, dict[str, str], Callable[[], Any], str]]:
    """(backend, environment, service context, why not run: '' when it runs)."""
    fd = VENV / 'fdsdk-emulator'
    libhd = VENV / 'lib' / 'haptic_topology' / 'libHD.so'
    haply = ROOT / 'haptic_topology' / 'remote' / 'haply_emulator.py'
    return [
        ('sim_maglev', {}, _nothing, ''),
        ('forcedimension', {'FDSDK': str(fd)}, _nothing,
         '' if fd.is_dir() else f'no emulator at {fd} (scripts/setup.sh builds it)'),
        ('openhaptics', {'HAPTIC_TOPOLOGY_LIBHD': str(libhd)}, _nothing,
         '' if libhd.is_file() else f'no emulator at {libhd} (scripts/setup.sh builds it)'),
        ('haply', {}, _haply_service,
         '' if haply.is_file() else 'no haply backend in this version'),
    ]


def run(duration: float, graph_loop: Callable[..., dict[str, Any]]) -> dict[str, Any]:
    """Each backend's run (module doc): ``{backend: figures}``, ``{backend}_failed`` or
    ``{backend}_skipped``."""
    res: dict[str, Any] = {}
    for name, env, service, why in backends():
        if why:
            print(f'== vendor loops, {name}: not run, {why}', flush=True)
            res[f'{name}_skipped'] = why
            continue
        print(f'== vendor loops, {SCENARIO} on {name}, {duration:g} s ...', flush=True)
        nodes = None if name == 'sim_maglev' else {'device_driver': _driver_params(name)}
        saved = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        try:
            with service():
                res[name] = graph_loop(duration, 'hosted', False, SCENARIO, nodes=nodes)
        except RuntimeError as exc:
            res[f'{name}_failed'] = str(exc).strip().splitlines()[-1][:300]
            print(f'== vendor loops, {name}: the run failed: {res[f"{name}_failed"]}',
                  flush=True)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    return res


def table(res: dict[str, Any], floor: dict[str, Any] | None) -> str:
    """One line per backend: its figures, and their ratios to sim_maglev's (and the
    floor's)."""
    ref = res.get('sim_maglev')
    lines = [f'vendor backends, {SCENARIO}, hosted: answered  missed in a row  period p99'
             '   (ratio to sim_maglev; to the floor)']
    for name, _, _, _ in backends():
        if name not in res:
            why = res.get(f'{name}_failed') or res.get(f'{name}_skipped') or 'not run'
            lines.append(f'  {name:15s} {why}')
            continue
        r = res[name]
        row = (f'  {name:15s} {100 * r["answered_fraction"]:7.2f} % '
               f'{r["max_consecutive_missed"]:6.0f} {r["period_p99_us"]:9.0f} us')
        for base in (ref, floor):
            if base:
                missed = r['max_consecutive_missed'] / max(1.0, base['max_consecutive_missed'])
                row += (f'   ({r["answered_fraction"] / base["answered_fraction"]:.4f}, '
                        f'{missed:.2f}, {r["period_p99_us"] / base["period_p99_us"]:.3f})')
        lines.append(row)
    return '\n'.join(lines)
