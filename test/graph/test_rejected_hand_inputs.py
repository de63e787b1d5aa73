"""``haptic-topology run`` when ``ve_sim`` rejects the controller's hand input batches: the
run ends in one line naming the rejection, as soon as the VE reports it, never with a
recorder time-out (the VE never takes a rejected batch, so the end of the run would wait in
vain for the VE to catch up with the controller).

``ve_sim:max_hand_wrench:=0.01`` (N) is below fig8's hand wrench (0.4 N), so the VE rejects
every batch of the run, on the wall clock and in lock-step (where the controller then waits for
an update that never comes). No time bound is asserted.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.graph


@pytest.mark.parametrize('clock', ['wall', 'lockstep'])
def test_a_run_whose_hand_inputs_the_ve_rejects_ends_with_the_reason(tmp_path: Path,
                                                                      clock: str) -> None:
    bag = tmp_path / 'bag'
    proc = subprocess.run(
        [sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8', '--duration', '2',
         '--clock', clock, '--no-plot', '--out', str(bag),
         '-p', 've_sim:max_hand_wrench:=0.01'],
        capture_output=True, timeout=240)
    out = (proc.stdout + proc.stderr).decode(errors='replace')
    assert proc.returncode == 1, out
    first = ('(the first: HandInputs.hand_wrench must be within +-0.01, got [0.4, 0.0, 0.0] '
             '(sample 0)); the VE did not take their inputs, so the run was stopped (bag: '
             f'{bag})')
    assert 'haptic-topology run: error: ve_sim rejected ' in out and first in out, out
    assert 'recorder has every message' not in out and 'Traceback' not in out, out
    assert (bag / 'logs' / 've_sim.log').is_file()
