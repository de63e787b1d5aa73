"""The machine's floor for the 1 kHz loop: ``bench/floor.c`` (a compiled loop that only sleeps
to absolute 1 ms deadlines, as ``cyclictest`` does), built with the machine's ``gcc`` and run
in the same ``make bench`` session as the graph's loop, so that each loop figure can be read
beside what the machine itself gives a loop that does nothing.

Run alone: ``.venv/bin/python bench/floor.py --duration 30 [--fifo 50]`` (prints one JSON
object; see ``floor.c`` for the figures).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

SOURCE = Path(__file__).resolve().with_name('floor.c')


def run(duration: float, fifo_priority: int = 0) -> dict[str, Any]:
    """Build and run the floor loop for ``duration`` s (``fifo_priority`` > 0: under
    SCHED_FIFO at that priority); its figures, with the graph's key names (rtt: NaN)."""
    gcc = shutil.which('gcc')
    if gcc is None:
        raise RuntimeError('bench/floor.py: gcc not found (it builds the floor loop)')
    with tempfile.TemporaryDirectory(prefix='bench_floor_') as tmp:
        exe = Path(tmp) / 'floor'
        subprocess.run([gcc, '-O2', '-o', str(exe), str(SOURCE)], check=True)
        res = subprocess.run([str(exe), str(duration), str(fifo_priority)],
                             capture_output=True, text=True, timeout=duration + 60,
                             check=False)
    if res.returncode != 0:
        raise RuntimeError(f'floor loop failed ({res.returncode}): {res.stderr.strip()}')
    out: dict[str, Any] = json.loads(res.stdout)
    out.update(rtt_p50_us=float('nan'), rtt_p99_us=float('nan'), rtt_max_us=float('nan'))
    return out


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--duration', type=float, default=30.0)
    ap.add_argument('--fifo', type=int, default=0, help='SCHED_FIFO priority (0: none)')
    a = ap.parse_args()
    print(json.dumps(run(a.duration, a.fifo), indent=2))
